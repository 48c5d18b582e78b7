"""``minidem verify LAW``: the seed paper's verification battery, run on any registered law.

Each check is a physical statement with its source; the battery runs the paper's
oblique impact (R = 25 mm, 2650 kg/m^3, E = 70 GPa, nu = 0.3, mu = 0.1, 5 m/s) with
the law under test, plus whatever ``--set`` overrides the user gives (e.g. a plugin
law's own parameters).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path

import numba
import numpy as np

from minidem.contact import laws
from minidem.errors import MinidemError
from minidem.results import analysis
from minidem.scene import scenario
from minidem.engine import law_signature, run_loop, simulation

PAPER_SCENE = {
    "materials": {"paper": {"youngs_modulus": 70e9, "poisson_ratio": 0.3, "density": 2650.0}},
    "contact": {"law": "hmd", "friction": 0.1},
    "walls": [{"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0], "material": "paper"}],
    "impact": {"material": "paper", "radius": 0.025, "speed": 5.0, "angle_deg": 30.0},
    "run": {"dt": "auto"},
}
PAPER_ANGLES = (0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 15.0, 20.0, 25.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0)
SLIDING_ANGLES = (60.0, 70.0, 80.0)


@dataclasses.dataclass
class Check:
    name: str
    passed: bool | None  # None: not applicable / information only
    value: str
    criterion: str
    source: str

    def __post_init__(self):
        if self.passed is not None:
            self.passed = bool(self.passed)  # numpy bools would not serialise to JSON


class Battery:
    def __init__(self, law_name: str, overrides: list[str] = ()):
        named = laws.registry().entry(law_name)
        base = copy.deepcopy(PAPER_SCENE)
        if not any(p.name == "friction" for p in named.law.parameters):
            # the paper's mu = 0.1 is for a law with friction: a frictionless law refuses the key
            del base["contact"]["friction"]
        self.base = scenario.apply_overrides(base, [f'contact.law="{named.law.name}"', *overrides])
        # the law the scenes run: the named one with the parts the overrides add
        # (--set contact.rolling=epsd makes hm the combination hm+epsd, whose history,
        # parameters and parts every check must see)
        self.entry = self._entry_as_run(named)
        self.law = self.entry.law
        # mu of the law under test, the paper's for a law without friction (the HMD runs
        # it is compared with, and the rigid-body lines of the report, take it)
        self.friction = float(self.base["contact"].get("friction", PAPER_SCENE["contact"]["friction"]))

    def _entry_as_run(self, named: laws.RegisteredLaw) -> laws.RegisteredLaw:
        try:
            scene = scenario.build_scene(copy.deepcopy(self.base), source=f"<verify {named.law.name}>",
                                         output_directory="-")
        except MinidemError:  # bad values: the checks that build the scene report them
            return named
        return laws.registry().entry(scene.law_name)

    def run(self, *extra: str, law: str | None = None, trace: bool = False) -> tuple[dict, run_loop.RunResult]:
        data = scenario.apply_overrides(self.base, list(extra))
        if law is not None:
            data["contact"] = {"law": law, "friction": self.friction}
        if trace:
            data.setdefault("output", {})["trace"] = True
        scene = scenario.build_scene(copy.deepcopy(data), source=f"<verify {self.law.name}>", output_directory="-")
        result = simulation.Simulation(scene).run()
        summary = analysis.summary(result)
        if scene.impact is not None and scene.stop == "separation" and summary["en"] is None:
            # every check that runs an impact to its separation measures its rebound (a
            # None in their arithmetic was a TypeError traceback; the adhesion check runs
            # to a time, for a sphere that may stick)
            raise laws.LawError(f"law '{self.law.name}': the impact at {scene.impact.angle_deg:g} deg has no rebound "
                                f"to measure: {analysis.incomplete_contact(result)}; the checks measure rebounds "
                                "(a contact that outlasts the law's contact_time a hundredfold, or a sphere that "
                                "sticks)")
        return summary, result

    def has_parameter(self, name: str) -> bool:
        return any(p.name == name for p in self.law.parameters)

    def adhesive_parts(self) -> list:
        """The parts that may supply energy (energy role "supply": adhesion)."""
        return [p for p in self.law.parts if "supply" in p.energy]

    def skipped_for_adhesion(self, name: str, assumption: str) -> list[Check] | None:
        """A check whose premise is a passive, tension-free contact: skipped (and why) for
        a combination with an adhesive part."""
        adhesive = self.adhesive_parts()
        if not adhesive:
            return None
        return [Check(name, None, f"skipped: the combination has an adhesive {adhesive[0].kind} part "
                      f"'{adhesive[0].name}'", f"not applicable: {assumption}", "the part's energy role 'supply'")]

    # -- the checks ---------------------------------------------------------------
    def energy(self) -> list[Check]:
        elastic = ["contact.restitution=1.0"] if self.has_parameter("restitution") else []
        # Judged against the gain velocity Verlet alone explains, the engine's own bound
        # (analysis.energy_gain_bound: 10 (dt/tc)^2, at least 1e-6), not a fixed 1e-9, which
        # holds only where dt divides the contact into whole steps: a sound law whose
        # contact ends mid-step gains ~1e-7, the integral form of the paper's Fig 12 1e-2.
        # That bound grows with dt/tc, so an impact of a few steps (a contact_time missing
        # or wrong) is not judged but fails: its bound would hide a gain of 7 %.
        gains, unresolved = {}, []
        for angle in PAPER_ANGLES:
            summary, result = self.run(f"impact.angle_deg={angle}", *elastic)
            bound = analysis.energy_gain_bound(summary["dt_s"], summary["contact_duration_s"] or math.inf)
            gains[angle] = (summary["energy_ratio"] - 1.0, bound)
            if analysis.resolution_warning(result, summary["contact_duration_s"]):
                unresolved.append((angle, summary["contact_duration_s"] / summary["dt_s"]))
        source = ("an elastic contact can only store and return energy; the paper's Fig 12 shows the integral form "
                  "violating this")
        if unresolved:
            angle, steps = unresolved[0]
            energy = Check("elastic impacts create no energy", False,
                           f"not judged: the contact lasted {steps:.3g} steps at {angle:g} deg (under-resolved at "
                           f"{len(unresolved)} of {len(PAPER_ANGLES)} angles)",
                           "every impact resolved in at least a tenth of run.steps_per_contact steps",
                           "the time step run.dt = \"auto\" takes from the law's contact_time (Hertz's when it "
                           "declares none): docs/writing-a-contact-law.md")
        else:
            worst = max(gains, key=lambda a: gains[a][0] / gains[a][1])
            gain, bound = gains[worst]
            energy = Check("elastic impacts create no energy", gain <= bound,
                           f"energy ratio {1.0 + gain:.10f} at {worst:g} deg, the closest to its integration bound "
                           f"{bound:.2g}",
                           "energy ratio <= 1 + integration error (10 (dt/tc)^2, at least 1e-6) at every angle", source)
        checks = [energy]
        skipped = self.skipped_for_adhesion("restitution 0.5 reproduced (normal impact)",
                                            "the damping part maps restitution for a spring without adhesion")
        if skipped:
            checks += skipped
        elif self.has_parameter("restitution"):
            en = self.run("impact.angle_deg=0.0", "contact.restitution=0.5")[0]["en"]
            checks.append(Check("restitution 0.5 reproduced (normal impact)", abs(en - 0.5) <= 0.005,
                                f"en = {en:.5f}", "|en - 0.5| <= 1 %", "the law's declared restitution mapping"))
        return checks

    def sliding_limit(self) -> list[Check]:
        skipped = self.skipped_for_adhesion("rigid-body sliding limit", "paper eqs 6-8 assume Coulomb's limit "
                                            "mu Fn on a normal force that is never tensile")
        if skipped:
            return skipped
        resisting = [f"the combination has a {p.kind} part '{p.name}'" for p in self.law.parts
                     if p.kind in ("rolling", "twisting")]
        if not resisting and self.law.couples:  # a whole law with its own couple (couples=True)
            resisting = ["the law returns a couple (couples=True)"]
        if resisting:  # eqs 6-8 have only the tangential force turn the sphere
            return [Check("rigid-body sliding limit", None, f"skipped: {resisting[0]}",
                          "not applicable: paper eqs 6-8 assume no rolling or twisting resistance",
                          "paper eqs 6-8")]
        if not self.has_parameter("friction"):
            return [Check("rigid-body sliding limit", None, "skipped: the law has no friction parameter",
                          "not applicable: paper eqs 6-8 are the limit of Coulomb friction", "paper eqs 6-8")]
        mu, worst = self.friction, 0.0
        for angle in SLIDING_ANGLES:
            s = self.run(f"impact.angle_deg={angle}")[0]
            expected_et = 1.0 - mu * (1.0 + s["en"]) / math.tan(math.radians(angle))
            worst = max(worst, abs(s["y1"] - (s["x"] - 7 * mu)), abs(s["y2"] + 5 * mu), abs(s["et"] - expected_et))
        return [Check("rigid-body sliding limit", worst <= 1e-3, f"max deviation {worst:.2e}",
                      "|y1-(x-7mu)|, |y2+5mu|, |et-(1-mu(1+en)/tan)| <= 1e-3 at 60, 70, 80 deg",
                      "paper eqs 6-8 (gross sliding throughout the impact)")]

    def duration(self) -> list[Check]:
        skipped = self.skipped_for_adhesion("normal-impact duration", "adhesion lengthens the contact beyond the "
                                            "normal part's contact_time (JKR forms at touch and breaks apart)")
        if skipped:
            return skipped
        if self.law.contact_time is None and "hertz" not in (self.law.reference + self.law.description).lower():
            return [Check("normal-impact duration", None, "law declares no contact_time", "-", "-")]
        summary, result = self.run("impact.angle_deg=0.0", *(["contact.restitution=1.0"]
                                                             if self.has_parameter("restitution") else []))
        scene = result.scene
        radius, mass = float(scene.radius[0]), float(scene.mass[0])
        pair, _, constants = self.prepared(scene, radius, mass)
        expected = laws.law_contact_time(self.law, pair, constants, radius, mass, 5.0)
        error = summary["contact_duration_s"] / expected - 1.0
        return [Check("normal-impact duration", abs(error) <= 5e-3,
                      f"{summary['contact_duration_s']:.6g} s vs {expected:.6g} s ({error:+.2%})", "within 0.5 %",
                      "the law's own contact_time (Hertz eq 13 when it declares none)")]

    def prepared(self, scene, radius: float, mass: float):
        """(the pair of the scene's sphere and its wall, the law's constants as the force
        function reads them, the same by name), at the impact's 5 m/s: a prepare() that
        fails is reported as ``minidem run`` reports it (exit 2), not as a failed check."""
        material = scene.materials[0]
        pair = laws.ContactPair.from_materials(material, material, radius, mass, 5.0)
        row, constants = laws.prepare_for_pair(self.law, self.entry.distribution, pair, scene.law_parameters,
                                               f"'{material.name}'/'{material.name}'")
        return pair, row, constants

    def history_bounds(self) -> list[Check]:
        """The force function writes only the history slots the law declares
        (``laws.history_overrun``: numba does not check array bounds, and a write past
        them would land in the next contact's row, or past the array, unnoticed)."""
        scene = scenario.build_scene(copy.deepcopy(self.base), source=f"<verify {self.law.name}>",
                                     output_directory="-")
        radius, mass = float(scene.radius[0]), float(scene.mass[0])
        pair, row, constants = self.prepared(scene, radius, mass)
        duration = laws.law_contact_time(self.law, pair, constants, radius, mass, 5.0)
        size = self.law.history_size
        try:
            passed, detail = laws.history_overrun(self.law, row, radius, mass, duration)
        except numba.core.errors.NumbaError as exc:  # the force does not compile: say where, exit 2
            raise law_signature.law_error(self.law, self.entry, exc) from exc
        # not judged (the force raised on this smooth path) fails here: the battery's
        # engine runs would call it on history rows it may overrun
        return [Check("history stays in its declared slots", passed is True, detail, f"writes only history[0:{size}]",
                      "the law's HistorySlot declarations (docs/writing-a-contact-law.md)")]

    def adhesion(self) -> list[Check]:
        """An adhesive combination: a normal impact slow enough for adhesion to matter
        (1/2 m v^2 = 4 times the supply bound, so the sphere still rebounds) must pass
        through the declared pull-off force, and the kinetic energy may exceed its
        initial value by at most the supply bound, there and in an impact 16 times
        slower in energy (which sticks: the sphere oscillates in the adhesive well)."""
        adhesive = self.adhesive_parts()
        names = ("adhesion: pull-off force", "adhesion: energy bounded by the adhesion work")
        if not adhesive:
            return [Check(name, None, "skipped: no part of the combination supplies energy (no adhesion)",
                          "applies to parts with the energy role 'supply'", "-") for name in names]
        scene = scenario.build_scene(copy.deepcopy(self.base), source=f"<verify {self.law.name}>",
                                     output_directory="-")
        radius, mass, inertia = float(scene.radius[0]), float(scene.mass[0]), float(scene.inertia[0])
        pair, _, constants = self.prepared(scene, radius, mass)
        bound = float(self.law.supply_bound(pair, constants, radius))
        elastic = ["contact.restitution=1.0"] if self.has_parameter("restitution") else []
        checks, worst, runs = [], -math.inf, []
        for energy_factor in (4.0, 1.0 / 16.0):
            speed = math.sqrt(2.0 * energy_factor * bound / mass)
            duration = laws.law_contact_time(self.law, pair, constants, radius, mass, speed)
            _, result = self.run("impact.angle_deg=0.0", f"impact.speed={speed!r}", "run.stop=\"time\"",
                                 f"run.end_time={20.0 * duration!r}", *elastic, trace=True)
            trace = result.trace
            kinetic = (0.5 * mass * np.sum(trace[:, 9:12] ** 2, axis=1)
                       + 0.5 * inertia * np.sum(trace[:, 12:15] ** 2, axis=1))
            initial = 0.5 * mass * speed**2
            worst = max(worst, (float(kinetic.max()) - initial) / bound)
            runs.append((speed, trace))
        checks_pull = []
        speed, trace = runs[0]
        for part in adhesive:
            if part.pull_off is None:
                checks_pull.append(Check(names[0], None, f"skipped: part '{part.name}' declares no pull_off", "-", "-"))
                continue
            own = {c: constants[f"{part.kind}.{c}"] for c in part.constants}
            expected = float(part.pull_off(pair, own, radius))
            measured = -float(trace[:, 2].min())
            error = measured / expected - 1.0
            checks_pull.append(Check(names[0], abs(error) <= 0.01,
                                     f"{measured:.6g} N vs {expected:.6g} N ({error:+.2%}) at {speed:.3g} m/s",
                                     "largest tensile force within 1 % of the part's pull_off",
                                     f"part '{part.name}': {part.reference}"))
        checks += checks_pull
        checks.append(Check(names[1], worst <= 1.0 + 1e-3,
                            f"largest gain of kinetic energy {worst:.4f} of the supply bound {bound:.3g} J",
                            "<= the parts' supply_bound (+0.1 % integration error), in a rebound and in a sticking "
                            "impact", "the parts' declared energy role 'supply' and its bound"))
        return checks

    def against_hmd(self) -> tuple[list[Check], dict]:
        curves = {"angle_deg": list(PAPER_ANGLES)}
        for law in (self.law.name, "hmd"):
            rows = [self.run(f"impact.angle_deg={a}", law=None if law == self.law.name else law)[0] for a in PAPER_ANGLES]
            curves[law] = {k: [r[k] for r in rows] for k in ("x", "y1", "y2", "et")}
        deviation = {k: float(np.nanmax(np.abs(np.array(curves[self.law.name][k], dtype=float)
                                               - np.array(curves["hmd"][k], dtype=float)))) for k in ("y1", "y2", "et")}
        text = ", ".join(f"{k} {v:.3g}" for k, v in deviation.items())
        return [Check("deviation from HMD over the paper's angles", None, f"max |diff|: {text}",
                      "information (HMD is the paper's reference law)", "paper Figs 5-10")], curves

    def first_loop(self) -> tuple[list[Check], np.ndarray]:
        _, result = self.run("impact.angle_deg=5.0", trace=True)
        trace = result.trace
        force, displacement = trace[:, 3], trace[:, 6]  # spring force and total displacement along x
        # the first loop closes when the displacement first returns to zero (paper Fig 12)
        start = int(np.argmax(np.abs(displacement) > 0))
        crossing = np.flatnonzero(np.sign(displacement[start + 1:]) != np.sign(displacement[start]))
        end = start + 1 + int(crossing[0]) if crossing.size else len(displacement) - 1
        # work done ON the sphere by the tangential force: the sphere feels -Ft
        work = -float(np.sum(0.5 * (force[1:end + 1] + force[:end]) * np.diff(displacement[:end + 1])))
        kinetic = 0.5 * float(result.scene.mass[0]) * 25.0
        # 1e-7 of the impact energy: far above the O(dt^2) quadrature error of an elastic
        # loop (~1e-9), far below what the integral form creates (~1e-3)
        return [Check("5 deg force-displacement loop creates no energy", work <= 1e-7 * kinetic,
                      f"work of Ft on the sphere over the first loop {work:+.3e} J",
                      "<= 1e-7 of the impact energy",
                      "paper section 5 and Fig 12")], trace

    def convergence(self) -> list[Check]:
        worst = 0.0
        for angle in (5.0, 20.0, 45.0):
            coarse = self.run(f"impact.angle_deg={angle}")[0]
            default_steps = next(k.default for k in scenario.SCHEMA["run"][1] if k.name == "steps_per_contact")
            fine = self.run(f"impact.angle_deg={angle}", f"run.steps_per_contact={2 * default_steps}")[0]
            worst = max(worst, *(abs(coarse[k] - fine[k]) for k in ("y1", "y2", "et")))
        return [Check("converged in the time step", worst < 1e-4, f"max change on halving dt {worst:.2e}",
                      "< 1e-4 in y1, y2, et at 5, 20, 45 deg", "issue 3: results must not depend on dt")]


    def pair_collision(self) -> list[Check]:
        """An oblique sphere-sphere collision (unequal radii, both spinning, a generic
        line of centres), then the same collision rotated and shifted."""
        rotation = _rotation(np.array([1.0, 2.0, 3.0]), 0.7)  # arbitrary, not about a coordinate axis
        shift = np.array([0.3, -0.2, 0.1])
        try:
            original = self.run_pair(np.eye(3), np.zeros(3))
        except laws.LawError as exc:  # e.g. a law that calibrates from the [impact] speed alone
            return [Check("sphere-sphere collision", None, f"not run: {exc}", "-", "-")]
        turned = self.run_pair(rotation, shift)
        scene = original.scene
        mass, inertia = scene.mass, scene.inertia

        def momenta(position, velocity, angular_velocity):
            linear = (mass[:, None] * velocity).sum(axis=0)
            angular = (np.cross(position, mass[:, None] * velocity) + inertia[:, None] * angular_velocity).sum(axis=0)
            return linear, angular

        p0, l0 = momenta(scene.position, scene.velocity, scene.angular_velocity)
        p1, l1 = momenta(original.position, original.velocity, original.angular_velocity)
        p_scale = float(np.sum(mass * np.linalg.norm(scene.velocity, axis=1)))
        l_scale = p_scale * float(scene.radius.sum()) + float(np.sum(inertia * np.linalg.norm(scene.angular_velocity,
                                                                                             axis=1)))
        # round-off: each step adds ~1e-16 relative, as a random walk (the same bound as
        # tests/test_multiparticle.py)
        roundoff = 1e-13 * original.steps ** 0.5
        drift = max(float(np.abs(p1 - p0).max()) / p_scale, float(np.abs(l1 - l0).max()) / l_scale)
        # forces in mid-contact: equal and opposite, and their moments cancel the torques
        duration = original.last_separation_time - original.first_contact_time
        middle = self.run_pair(np.eye(3), np.zeros(3), end_time=original.first_contact_time + 0.5 * duration)
        force, torque, position = middle.force, middle.torque, middle.position
        force_scale = float(np.abs(force).max())
        imbalance = max(float(np.abs(force.sum(axis=0)).max()) / force_scale,
                        float(np.abs((np.cross(position, force) + torque).sum(axis=0)).max())
                        / (force_scale * float(scene.radius.sum())))
        # frame invariance: the rotated run must give the rotated result
        speed = float(np.abs(scene.velocity).max())
        spin = float(np.abs(scene.angular_velocity).max())
        difference = max(
            float(np.abs(turned.velocity - original.velocity @ rotation.T).max()) / speed,
            float(np.abs(turned.angular_velocity - original.angular_velocity @ rotation.T).max()) / spin,
            float(np.abs(turned.position - (original.position @ rotation.T + shift)).max()) / float(scene.radius[0]))
        changed = float(np.abs(original.angular_velocity - scene.angular_velocity).max()) / spin
        return [
            Check("sphere-sphere collision conserves momentum and angular momentum", drift <= roundoff,
                  f"relative change {drift:.2e} over {original.steps} steps (spins changed by {changed:.2f} of the "
                  "largest)", f"<= 1e-13 sqrt(steps) = {roundoff:.1e} (round-off)",
                  "Newton's third law and lever arms summing to the centre distance"),
            Check("sphere-sphere forces equal and opposite", imbalance <= 1e-12,
                  f"|F1 + F2|, |sum(x x F + T)| relative {imbalance:.2e} in mid-contact", "<= 1e-12 (round-off)",
                  "action and reaction"),
            Check("frame invariance (rotated collision)", difference <= 1e-9,
                  f"max relative difference {difference:.2e}", "<= 1e-9 of the speed, spin and radius",
                  "a contact law may depend only on relative quantities: rotating and shifting the scene "
                  "rotates and shifts the result"),
        ]

    def exchange(self) -> list[Check]:
        """The oblique collision of :meth:`pair_collision` with the two spheres' order
        reversed at every list build, so that the contact is carried each time to the pair
        seen from its other sphere with the law's HistorySlot.exchange signs, against the
        same run left in its order."""
        name = "history read from the other sphere (HistorySlot.exchange)"
        source = "a contact's force does not depend on which of its spheres is the first (docs/writing-a-contact-law.md)"
        if not self.law.history_size:
            return [Check(name, None, "skipped: the law keeps no history", "-", "-")]
        signs = self.law.exchange_signs
        if signs is None:
            undeclared = ", ".join(slot.name for slot in self.law.history if slot.exchange is None)
            return [Check(name, None, f"not declared for slot(s) {undeclared}: a run with this law keeps the order "
                          "it starts in (never sorted in space again as its particles mix)", "-", source)]
        try:
            first = self.run_pair(np.eye(3), np.zeros(3))
        except laws.LawError as exc:
            return [Check(name, None, f"not run: {exc}", "-", "-")]
        end_time = 1.05 * first.last_separation_time if first.separated else first.time
        plain, _ = self.run_turning(end_time, turn=False)
        turned, sorts = self.run_turning(end_time, turn=True)
        speed, spin = float(np.abs(plain.velocity).max()), float(np.abs(plain.angular_velocity).max())
        difference = max(float(np.abs(turned.velocity - plain.velocity).max()) / speed,
                         float(np.abs(turned.angular_velocity - plain.angular_velocity).max()) / spin)
        return [Check(name, difference <= 1e-9 and sorts >= 10,
                      f"max relative difference {difference:.2e} over {sorts} reversals (the run: the contact)",
                      "<= 1e-9 of the speed and spin (round-off), at least 10 reversals", source)]

    def run_pair(self, rotation: np.ndarray, shift: np.ndarray, end_time: float | None = None):
        """The oblique pair collision, rotated and shifted (to separation, or to ``end_time``)."""
        data = self.pair_data(rotation, shift, end_time)
        return simulation.Simulation(self.pair_scene(data)).run()

    def run_turning(self, end_time: float, turn: bool) -> tuple[run_loop.RunResult, int]:
        """The pair collision with a list rebuild about every 20 steps (a 2 um skin), the two
        spheres' order reversed at every rebuild when ``turn``: (the run, how many times it
        was sorted). Sorting and the exchange of a pair's history are the same code for two
        spheres as for many (Simulation.sort_in_space), and two run on the kernel the other
        checks of the pair already compiled."""
        data = self.pair_data(np.eye(3), np.zeros(3), end_time)
        data["run"]["skin"] = 2e-6
        sim = simulation.Simulation(self.pair_scene(data))
        if turn:
            sim.exchange_signs, sim.resort_ratio = np.array(self.law.exchange_signs), 0.0
            sim.space_order = lambda position: np.arange(position.shape[0])[::-1].copy()
        return sim.run(), sim.state.sorts

    def pair_scene(self, data: dict):
        return scenario.build_scene(data, source=f"<verify {self.law.name}: sphere-sphere>", output_directory="-")

    def pair_data(self, rotation: np.ndarray, shift: np.ndarray, end_time: float | None) -> dict:
        """The scenario of the oblique pair collision: unequal radii, both spinning, a
        generic line of centres, rotated and shifted."""
        radii = (0.025, 0.02)
        mass = [r ** 3 for r in radii]  # same density: the mass ratio
        normal = np.array([1.0, 0.5, -0.3]) / np.linalg.norm([1.0, 0.5, -0.3])
        tangent = np.cross(normal, [0.0, 0.0, 1.0])
        tangent /= np.linalg.norm(tangent)
        angle = math.radians(30.0)
        relative = 5.0 * (math.cos(angle) * normal + math.sin(angle) * tangent)
        # 1 um apart: exactly touching would leave the first touch to round-off
        position = [-(radii[0] + 0.5e-6) * normal, (radii[1] + 0.5e-6) * normal]
        velocity = [mass[1] / sum(mass) * relative, -mass[0] / sum(mass) * relative]  # centre of mass at rest
        spin = [np.array([0.0, 50.0, 20.0]), np.array([10.0, 0.0, -30.0])]
        # no gravity: the forces on the pair are then the contact's alone
        run = dict(self.base.get("run", {}), stop="separation", gravity=[0.0, 0.0, 0.0])
        if end_time is not None:
            run.update(stop="time", end_time=end_time)
        contact = copy.deepcopy(self.base["contact"])
        if self.has_parameter("calibration_speed") and contact.get("calibration_speed") is None:
            contact["calibration_speed"] = self.base["impact"]["speed"]  # as the impacts calibrate
        material = next(iter(self.base["materials"]))
        data = {
            "materials": copy.deepcopy(self.base["materials"]),
            "contact": contact,
            "particles": [{"position": (rotation @ position[i] + shift).tolist(),
                           "velocity": (rotation @ velocity[i]).tolist(),
                           "angular_velocity": (rotation @ spin[i]).tolist(), "radius": radii[i],
                           "material": material} for i in range(2)],
            "run": run,
            "output": {"vtk": False},
        }
        return data


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix about ``axis`` by ``angle`` rad (Rodrigues)."""
    k = axis / np.linalg.norm(axis)
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * cross @ cross


def run_battery(law_name: str, overrides: list[str] = (), out_directory: Path | None = None) -> list[Check]:
    return run_checks(Battery(law_name, overrides), out_directory)


def run_checks(battery: Battery, out_directory: Path | None = None, progress=None) -> list[Check]:
    """Every check of the battery, and its report in ``out_directory`` (None: none).
    ``progress(text)``: told which checks run next (the CLI prints it: the battery
    compiles kernels and runs tens of impacts, tens of seconds on a fresh install).

    A force that writes past its declared history slots ends the battery there, with
    that check failed: every later check runs it in the engine, whose history rows it
    would overrun (numba checks no bounds), and the process died on a corrupted heap
    before the table was printed (free(): invalid next size)."""
    tell = progress or (lambda text: None)
    tell("the history slots")
    checks = battery.history_bounds()
    if not all(c.passed for c in checks):
        if out_directory is not None:
            _write_report(out_directory, battery, checks, None, None)
        return checks
    tell("energy, sliding limit, contact duration, adhesion")
    checks += battery.energy() + battery.sliding_limit() + battery.duration()
    checks += battery.adhesion()
    tell("the paper's angles against hmd, the first load-unload loop, convergence")
    comparison, curves = battery.against_hmd()
    loop, trace = battery.first_loop()
    checks += comparison + loop + battery.convergence()
    tell("a two-sphere collision, and the same with the spheres' order reversed")
    checks += battery.pair_collision() + battery.exchange()
    if out_directory is not None:
        _write_report(out_directory, battery, checks, curves, trace)
    return checks


def report_files(directory: Path, checks: list[Check]) -> list[Path]:
    """The files of the report ``run_checks`` wrote for ``checks``: no figure when the
    battery ended at its first check."""
    stopped = len(checks) == 1 and checks[0].passed is False
    return [Path(directory) / "verify.json"] + ([] if stopped else [Path(directory) / "verify.png"])


def _write_report(directory: Path, battery: Battery, checks: list[Check], curves: dict, trace: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from minidem import files

    files.write_json(Path(directory) / "verify.json", {
        "law": battery.law.name, "package": battery.entry.distribution, "version": battery.entry.version,
        "checks": [dataclasses.asdict(c) for c in checks], "curves": curves})
    if curves is None:  # the battery ended at its first check (run_checks): nothing to draw
        return
    mu = battery.friction
    fig, axes = plt.subplots(1, 4, figsize=(18, 4.2))
    x = np.linspace(0, max(curves["hmd"]["x"]), 50)
    for ax, key, line in ((axes[0], "y1", x - 7 * mu), (axes[1], "y2", np.full_like(x, -5 * mu))):
        for law in (battery.law.name, "hmd"):
            ax.plot(curves[law]["x"], curves[law][key], "o-", ms=3, label=law)
        ax.plot(x, line, "k:", label="gross sliding (eqs 6-8)")
        ax.set_xlabel("x = 2 tan(theta)/(1+en)")
        ax.set_ylabel(key)
        ax.legend()
    for law in (battery.law.name, "hmd"):
        axes[2].plot(curves["angle_deg"], curves[law]["et"], "o-", ms=3, label=law)
    axes[2].set_xlabel("impact angle (deg)")
    axes[2].set_ylabel("et")
    axes[2].legend()
    axes[3].plot(trace[:, 6] * 1e6, trace[:, 3], "-")
    axes[3].set_xlabel("tangential displacement (um)")
    axes[3].set_ylabel("tangential force (N)")
    axes[3].set_title("5 deg impact")
    fig.suptitle(f"minidem verify {battery.law.name} ({battery.entry.distribution} {battery.entry.version})")
    fig.tight_layout()
    fig.savefig(Path(directory) / "verify.png", dpi=110)
    plt.close(fig)


def format_table(checks: list[Check]) -> str:
    width = max(len(c.name) for c in checks)
    lines = []
    for c in checks:
        mark = {True: "PASS", False: "FAIL", None: "info"}[c.passed]
        lines.append(f"  {mark}  {c.name:<{width}}  {c.value}  [{c.criterion}; {c.source}]")
    return "\n".join(lines)
