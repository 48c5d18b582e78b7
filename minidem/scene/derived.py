"""What a scenario's values imply, checked before anything is compiled or run.

Every key has its own bounds (``minidem.scene.scenario.SCHEMA``), but values inside their
bounds can still imply quantities a float64 computation cannot carry: a density of
1e-320 kg/m^3 gives a sphere of mass 0 (a division by zero at the first step), a
Young's modulus of 1e308 Pa an infinite effective modulus, an end time of 1e308 s more
steps than any machine will run. Each derived quantity (masses, moments of inertia,
kinetic energies, the contact constants, contact time, stability limit, time step and
step count) is checked here, and a bad one is a :class:`ScenarioError` (exit 2) that
names the keys it comes from, the most extreme value first.
"""

from __future__ import annotations

import contextlib
import math
import warnings

import numpy as np

from minidem.errors import ScenarioError

# an estimated overlap this many radii deep is refused (check_simulation; beyond one radius a warning)
REFUSED_OVERLAP = 10.0

# Most steps a run may have: 1e12 steps are a month at a single sphere's 4e5 steps/s
# (README); more is a mistaken end time, gap or time step, not a run to start.
MAX_STEPS = 10**12
# The time of a step, start_time + k dt, must resolve dt: a step below this fraction
# of the run's end time is lost to round-off (float64 carries ~16 digits).
MIN_RELATIVE_STEP = 1e-12
# An input more than this many decades from 1 in SI units (1e-40 m, 1e40 Pa) is taken
# as the cause when a law's arithmetic overflows on it.
EXTREME_DECADES = 40.0


def _is_positive_finite(value) -> bool:
    return isinstance(value, (int, float, np.floating)) and math.isfinite(value) and value > 0.0


def _extremity(value: float) -> float:
    """How far a value is from ordinary magnitudes, in decades (0 and 1 are ordinary)."""
    value = abs(float(value))
    if not math.isfinite(value):
        return math.inf  # an overflowed input (a norm of 1e300 components) is the most extreme
    return 0.0 if value == 0.0 else abs(math.log10(value))


def _suspects(inputs: list[tuple[str, float]]) -> str:
    ranked = sorted(inputs, key=lambda kv: -_extremity(kv[1]))
    return ", ".join(f"{key} = {value:.6g}" for key, value in ranked)


def scene_inputs(scene) -> list[tuple[str, float]]:
    """(key, value) of every scalar input the constants and the time step are derived from."""
    inputs = []
    for m in scene.materials:
        inputs += [(f"materials.{m.name}.youngs_modulus", m.youngs_modulus),
                   (f"materials.{m.name}.poisson_ratio", m.poisson_ratio),
                   (f"materials.{m.name}.density", m.density)]
    if scene.n_particles:
        smallest, largest = int(np.argmin(scene.radius)), int(np.argmax(scene.radius))
        inputs.append((_key_of(scene.particle_name(smallest), "radius"), float(scene.radius[smallest])))
        if largest != smallest:
            inputs.append((_key_of(scene.particle_name(largest), "radius"), float(scene.radius[largest])))
    raw = scene.raw if isinstance(scene.raw, dict) else {}
    # the law's parameters (a restitution of 1e-20 is a damping ratio of 5e9, whose
    # stability limit underflows: a robustness review found the materials blamed)
    contact = raw.get("contact") if isinstance(raw.get("contact"), dict) else {}
    for key, value in contact.items():
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            inputs.append((f"contact.{key}", float(value)))
    for section, key in (("impact", "speed"), ("impact", "gap"), ("run", "dt"), ("run", "end_time"),
                         ("run", "skin")):
        value = raw.get(section, {}).get(key) if isinstance(raw.get(section), dict) else None
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            inputs.append((f"{section}.{key}", float(value)))
    if scene.n_particles:
        speeds = np.abs(scene.velocity).max(axis=1)
        fastest = int(np.argmax(speeds))
        if speeds[fastest] > 0.0 and scene.impact is None:
            inputs.append((_key_of(scene.particle_name(fastest), "velocity"), float(speeds[fastest])))
    gravity = float(np.abs(scene.gravity).max())  # the largest component: a norm could overflow
    if gravity > 0.0:
        inputs.append(("run.gravity", gravity))
    return inputs


def _key_of(particle: str, key: str) -> str:
    """The key of a particle's table: 'impact' -> 'impact.radius', 'fill[0] (...)' -> 'fill[0].radius'."""
    table = particle.split(" ", 1)[0]
    if table.startswith("fill[") and key == "velocity":
        return f"{table}.velocity (or the file's vx, vy, vz)"
    return f"{table}.speed" if table == "impact" and key == "velocity" else f"{table}.{key}"


def refusal(scene, what: str, inputs=None):
    """The ScenarioError for a derived quantity out of range: what it is, and the keys it
    comes from, the most extreme value first (that one is almost always the mistake)."""
    inputs = scene_inputs(scene) if inputs is None else inputs
    return ScenarioError(f"{scene.source}: {what}: out of the range of a float64 computation (or of a run); "
                         f"it comes from {_suspects(inputs)}; give values of ordinary magnitude (SI units)")


def check_scene(scene) -> None:
    """Each particle's mass, moment of inertia and kinetic energy finite and (mass,
    inertia) > 0; each material's shear modulus E / 2(1 + nu) finite and > 0."""
    with np.errstate(all="ignore"):
        for m in scene.materials:
            inputs = [(f"materials.{m.name}.youngs_modulus", m.youngs_modulus),
                      (f"materials.{m.name}.poisson_ratio", m.poisson_ratio)]
            shear = m.youngs_modulus / (2.0 * (1.0 + m.poisson_ratio))
            plane_strain = m.youngs_modulus / (1.0 - m.poisson_ratio**2) if m.poisson_ratio != 1.0 else math.inf
            for name, value in (("shear modulus E / 2(1 + nu)", shear),
                                ("plane-strain modulus E / (1 - nu^2)", plane_strain)):
                if not _is_positive_finite(value) and not (name.startswith("plane") and m.poisson_ratio == 1.0):
                    raise refusal(scene, f"material '{m.name}': {name} = {value:.6g} Pa", inputs)
        if not scene.n_particles:
            return
        density = np.array([m.density for m in scene.materials])[scene.particle_material]
        mass, inertia = scene.mass, scene.inertia
        energy = 0.5 * (mass * np.einsum("ik,ik->i", scene.velocity, scene.velocity)
                        + inertia * np.einsum("ik,ik->i", scene.angular_velocity, scene.angular_velocity))
        for name, values, keys in (("mass 4/3 pi r^3 rho", mass, ("radius", "density")),
                                   ("moment of inertia 2/5 m r^2", inertia, ("radius", "density")),
                                   ("kinetic energy", energy, ("radius", "density", "velocity"))):
            bad = np.flatnonzero(~np.isfinite(values) | ((values <= 0.0) if name != "kinetic energy" else False))
            if bad.size:
                i = int(bad[0])
                particle = scene.particle_name(i)
                material = scene.materials[scene.particle_material[i]].name
                inputs = []
                for key in keys:
                    if key == "radius":
                        inputs.append((_key_of(particle, "radius"), float(scene.radius[i])))
                    elif key == "density":
                        inputs.append((f"materials.{material}.density", float(density[i])))
                    elif particle == "impact":
                        inputs.append(("impact.speed", scene.impact.speed))
                        inputs.append(("impact.spin", float(scene.raw["impact"].get("spin", 0.0))))
                    else:
                        inputs.append((_key_of(particle, "velocity"), float(np.linalg.norm(scene.velocity[i]))))
                        inputs.append((_key_of(particle, "angular_velocity"),
                                       float(np.linalg.norm(scene.angular_velocity[i]))))
                more = f" (and {bad.size - 1} more particles)" if bad.size > 1 else ""
                raise refusal(scene, f"{particle}: {name} = {float(values[i]):.6g}{more}", inputs)


@contextlib.contextmanager
def arithmetic(scene, what: str):
    """Turn a float overflow or division by zero while deriving ``what`` into a refusal
    naming the inputs (numpy's warnings silenced: the results are checked after)."""
    from minidem.contact.laws import LawError

    with np.errstate(all="ignore"):
        try:
            yield
        except (ArithmeticError, ValueError) as exc:
            if isinstance(exc, ValueError) and "math domain error" not in str(exc):
                raise
            # nu = 1, accepted (issue 2: up to 1), divides by zero only where two bodies of
            # it touch: E / (1 - nu^2), not a value of extreme magnitude to name
            singular = [f"materials.{m.name}.poisson_ratio = 1" for m in scene.materials if m.poisson_ratio == 1.0]
            if singular:
                raise ScenarioError(
                    f"{scene.source}: {what} ({type(exc).__name__}: {exc}): {', '.join(singular)}: two bodies "
                    "of such a material have an infinite contact modulus E / (1 - nu^2); give a Poisson ratio "
                    "below 1 (the paper's kappa studies go up to 5/6), or the bodies it touches another material") from None
            raise refusal(scene, f"{what} ({type(exc).__name__}: {exc})") from None
        except LawError as exc:
            # a law whose prepare() or stiffness() overflowed on an extreme input (1e308 Pa):
            # the input is the mistake, not the law; with ordinary inputs the law is named
            if max((_extremity(v) for _, v in scene_inputs(scene)), default=0.0) < EXTREME_DECADES:
                raise
            raise refusal(scene, f"{what} ({exc})") from None


def check_simulation(sim) -> None:
    """The contact constants, contact time, stability limit, time step and step count of
    a Simulation (after its time step is chosen)."""
    scene = sim.scene
    if not np.all(np.isfinite(sim.constants)):
        raise refusal(scene, f"contact law '{sim.law.name}' constants {sim.constants.tolist()}")
    if not _is_positive_finite(sim.dt):
        raise refusal(scene, f"time step {sim.dt!r} s ({sim.dt_reason})")
    try:
        half_skin_squared = (0.5 * sim.skin) ** 2  # what the neighbour lists compare against
    except OverflowError:
        half_skin_squared = math.inf
    if not math.isfinite(half_skin_squared):
        raise refusal(scene, f"neighbour-list skin {sim.skin:.6g} m squared", [("run.skin", sim.skin)])
    ratio, overlap, radius, kind, cause = getattr(sim, "deepest_overlap", (0.0, 0.0, 0.0, "", ""))
    if ratio > 1.0:
        # an undamped upper bound, so beyond the radius is only a warning (a soft bead
        # dropped 1 m with e = 0.3 runs, at 0.7 of the bound); ten radii is no soft-sphere
        # contact however damped, and the sphere passes through a wall whatever the step (a
        # robustness review: it failed as "the time step is too large", and each smaller
        # step suggested failed the same way)
        inputs = [(key, value) for key, value in scene_inputs(scene)
                  if key.startswith(("materials.", "contact.normal_stiffness", "impact.speed", "run.gravity"))
                  or key.endswith((".radius", ".velocity"))]
        depth = (f"up to about {overlap:.3g} m" if math.isfinite(overlap)
                 else f"more than {sim.OVERLAP_SEARCH_RADII:g} radii")
        text = (f"{scene.source}: a {kind} contact would overlap by {depth} (the law's elastic force, undamped, at "
                f"{cause}), " + (f"{ratio:.3g} times" if math.isfinite(ratio) else "beyond")
                + f" the sphere's radius {radius:.3g} m")
        where = (f"It comes from {', '.join(f'{key} = {value:.6g}' for key, value in inputs)}: a stiffer material, "
                 "a slower impact or weaker gravity")
        if ratio > REFUSED_OVERLAP:
            raise ScenarioError(f"{text}: far beyond a soft-sphere contact, and no time step helps. {where}")
        warnings.warn(f"{text}: beyond what a soft-sphere contact describes (a dashpot keeps it shallower; a sphere "
                      f"pushed through a wall is then no matter of the time step). {where}", stacklevel=2)
    contact_time = sim.reference_contact_time
    if not (contact_time > 0.0):
        raise refusal(scene, f"contact time {contact_time!r} s")
    if scene.impact is not None and isinstance(scene.raw.get("impact"), dict):
        # the flight over impact.gap to first touch (at most gap / normal speed; gravity
        # towards the wall shortens it): a step must still resolve the time of the touch
        gap = float(scene.raw["impact"].get("gap", 0.0))
        normal_speed = scene.impact.speed * math.cos(math.radians(scene.impact.angle_deg))
        touch = max(sim.flight_time, sim.start_time)
        if gap > 0.0 and touch == 0.0:
            touch = gap / normal_speed if normal_speed > 0.0 else math.inf
        if not math.isfinite(touch) or sim.dt < MIN_RELATIVE_STEP * touch:
            raise refusal(scene, f"the sphere would touch the wall at t = {touch:.6g} s (impact.gap = {gap:.6g} m "
                          f"at {normal_speed:.6g} m/s towards it), where a time step of {sim.dt:.4g} s is below "
                          "the float64 resolution of the time", [("impact.gap", gap), ("impact.speed", scene.impact.speed)])
    end_time = sim.end_time
    if not math.isfinite(end_time):
        return  # no contact to stop at and no run.end_time: the run says so (exit 2)
    start = max(sim.start_time, 0.0)
    steps = (end_time - start) / sim.dt
    if not math.isfinite(steps) or steps > MAX_STEPS:
        raise refusal(scene, f"the run would take {steps:.3g} steps (t = {start:.6g} to {end_time:.6g} s at "
                      f"dt = {sim.dt:.4g} s; at most {MAX_STEPS:.0e} are run)")
    if sim.dt < MIN_RELATIVE_STEP * end_time:
        raise refusal(scene, f"the time step {sim.dt:.4g} s is below the float64 resolution of the run's times "
                      f"(up to {end_time:.6g} s: a step must be at least {MIN_RELATIVE_STEP:g} of it)")
