"""Rebound measures of an oblique impact (paper eqs 2 and 9) and energy balance."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the sweep's parent process reads rows without loading the engine
    from minidem.engine.run_loop import RunResult


def kinetic_energy(mass, inertia, velocity, angular_velocity) -> float:
    """Translational plus rotational kinetic energy of all particles (J)."""
    from minidem.engine import integrate  # here: importing analysis must not load numba (see above)

    # C-contiguous and writable, as the run's state passes them: numba compiles a function
    # once per argument types, and read-only counts as another type. The scene's initial
    # velocities are a read-only broadcast row when all are equal (scenario._Bodies.array),
    # and a read-only copy here cost a first run (scenarios/oblique.toml, whose summary
    # asks for the energy ratio) a second compilation of the kinetic energy, 0.2 s at its end.
    def engine_array(values):
        return np.require(values, dtype=np.float64, requirements=("C", "W"))

    return float(integrate.kinetic_energy(engine_array(mass), engine_array(inertia), engine_array(velocity),
                                          engine_array(angular_velocity)))


def energy_ratio(result: RunResult) -> float:
    scene = result.scene
    before = kinetic_energy(scene.mass, scene.inertia, result.initial_velocity, result.initial_angular_velocity)
    after = kinetic_energy(scene.mass, scene.inertia, result.velocity, result.angular_velocity)
    return after / before if before > 0 else math.nan


def rebound(result: RunResult) -> dict:
    """en, et, x, y1, y2 of particle 0 against the impact wall.

    With n the wall normal and t the tangential direction of travel, spin is measured
    about t x n, so that in gross sliding y2 = -5 mu (eq 8) and the rebound surface
    velocity is vtr = Vtr + R w_r (eq 9).
    """
    scene = result.scene
    impact = scene.impact
    n, t = impact.normal, impact.tangent
    radius = float(scene.radius[0])
    v0, w0 = result.initial_velocity[0], result.initial_angular_velocity[0]
    v1, w1 = result.velocity[0], result.angular_velocity[0]
    spin_axis = np.cross(t, n)
    normal_in, tangential_in = -float(v0 @ n), float(v0 @ t)
    normal_out, tangential_out = float(v1 @ n), float(v1 @ t)
    spin_out = float(w1 @ spin_axis)
    en = normal_out / normal_in
    et = tangential_out / tangential_in if tangential_in != 0.0 else math.nan
    surface_out = tangential_out + radius * spin_out
    scale = (1.0 + en) * normal_in
    return {
        "en": en,
        "et": et,
        "x": 2.0 * math.tan(math.radians(impact.angle_deg)) / (1.0 + en),
        "y1": 2.0 * surface_out / scale,
        "y2": 2.0 * radius * spin_out / scale,
        "initial_spin_rad_s": float(w0 @ spin_axis),
    }


# Velocity Verlet's energy error over a whole impact, measured for the frictionless
# normal impact (hm, hmd, ls; 20-2000 steps per contact): at most 1.7 (dt/tc)^2 (linear
# spring, 20 steps), 5e-10 at 2000 (the default is 4000). Ten times that, and never below 1e-6,
# is what a rebound may gain before the gain is the law's and not the integrator's.
ENERGY_GAIN_FACTOR = 10.0
ENERGY_GAIN_FLOOR = 1e-6


def energy_gain_bound(dt: float, contact_duration: float) -> float:
    """Largest energy ratio - 1 that integration error explains (see above)."""
    return max(ENERGY_GAIN_FLOOR, ENERGY_GAIN_FACTOR * (dt / contact_duration) ** 2)


def energy_creation_warning(law: str, ratio, dt, contact_duration) -> str | None:
    """A warning if an impact ended with more kinetic energy than it began with, beyond
    integration error: with no gravity and fixed walls only the contact law can have
    supplied it. None if it did not, or if the numbers needed are missing."""
    if ratio is None or dt is None or not contact_duration or not math.isfinite(ratio):
        return None
    bound = energy_gain_bound(dt, contact_duration)
    if ratio - 1.0 <= bound:
        return None
    return (f"energy ratio {ratio:.7g}: the impact ended with {ratio - 1.0:.2g} more kinetic energy than it "
            f"began with, beyond the integration error at this time step ({bound:.2g}): contact law '{law}' "
            "created energy (docs/laws.md, 'Laws that create energy')")


def incomplete_contact(result: RunResult) -> str | None:
    """Why the run has no complete rebound to report: the sphere of an impact never
    touched the wall, or a run meant to stop at separation stopped in contact."""
    scene = result.scene
    if scene.impact is not None and result.first_contact_time < 0:
        return f"no contact by t = {result.time:.4g} s (run.end_time): no rebound to measure"
    if not result.separated and scene.stop == "separation":
        limit = ("run.end_time" if scene.end_time is not None else
                 "the default run.end_time, 100 contact times")
        if result.contact_statistics and result.first_contact_time < 0:
            return (f"no contact by t = {result.time:.4g} s ({limit}): run.stop = \"separation\" had no contact "
                    "to wait for; to follow a scene as it falls or settles give run.stop = \"time\" and "
                    "run.end_time")
        return (f"the contacts had not ended by t = {result.time:.4g} s ({limit}; {result.contacts} contact(s) at "
                "the end)")
    if scene.impact is not None and result.contacts > 0:  # run.stop = "time": the rebound keys are null
        return (f"the impact's contact had not ended by t = {result.time:.4g} s (run.end_time): no rebound to "
                "measure")
    return None


def _impact_energy_warning(result: RunResult, ratio: float, duration) -> str | None:
    scene = result.scene
    if scene.impact is None or np.any(scene.gravity != 0.0) or not result.separated:
        return None  # gravity changes kinetic energy; an unfinished contact still stores some
    return energy_creation_warning(result.law.name, ratio, result.dt, duration)


def energy_budget_warning(result: RunResult) -> str | None:
    """A warning if a scene's kinetic energy ever exceeded what it could have: contacts
    are passive, so KE(t) <= KE(0) + the work gravity has done. The samples and that
    work are taken at the same steps (the run's checks). 1e-3 of the budget allows for
    integration error; the blow-up guard stops a run at twice the budget and a floor
    (minidem.blowup.ENERGY_FACTOR), so this warns of the smaller excesses in between."""
    scene = result.scene
    if scene.impact is not None or result.energy is None or len(result.energy) == 0:
        return None  # an impact's own check: energy_creation_warning
    initial, peak = float(result.energy[0, 1]), float(result.energy[:, 1].max())
    # adhesive parts (energy role "supply") may give up to their bound per contact
    budget = initial + max(result.gravity_work_max, 0.0) + result.supply_budget
    if peak <= budget * (1.0 + 1e-3):
        return None
    # below twice, the excess itself ("1.09 J, 1 times what the scene can supply" read as none)
    ratio = peak / budget if budget > 0.0 else math.inf
    times = (f"{100.0 * (ratio - 1.0):.3g} % more than" if ratio < 2.0 else
             f"{ratio:.3g} times" if math.isfinite(ratio) else "more than")
    what = ("the initial kinetic energy plus the work of gravity plus what adhesion can supply, "
            f"{result.supply_budget:.3g} J" if result.supply_budget else
            "the initial kinetic energy plus the work of gravity; contacts cannot add energy")
    return (f"the kinetic energy reached {peak:.3g} J, {times} what the scene can supply ({budget:.3g} J: "
            f"{what}): the time step is too large for the contacts, or the law creates energy beyond its declared "
            "role (docs/time-step.md)")


# An automatic time step is run.steps_per_contact steps of the contact time the law
# declares (or Hertz's, eq 13, when it declares none). A contact measured ten times
# shorter than that was not resolved as asked: the law's contact is not the one assumed.
UNDER_RESOLVED_FRACTION = 0.1


def resolution_warning(result: RunResult, duration) -> str | None:
    """A warning if the measured contact (an impact or a two-sphere collision) lasted fewer
    than UNDER_RESOLVED_FRACTION of the steps an automatic time step aims at: the contact
    time that dt was chosen from is not the law's (a plugin law that declares no
    contact_time gets the Hertz duration), and the rebound is under-resolved, however
    plausible it looks. None for a time step the scenario gave."""
    scene = result.scene
    if not duration or not result.dt or not str(result.dt_reason).startswith("auto"):
        return None
    steps = duration / result.dt
    if steps >= UNDER_RESOLVED_FRACTION * scene.steps_per_contact:
        return None
    law = result.law
    cause = (f"law '{law.name}' declares no contact_time, so the Hertz duration (eq 13) was assumed; a law of "
             "your own: declare contact_time (docs/writing-a-contact-law.md); any law: give run.dt"
             if law.contact_time is None else
             f"the contact time law '{law.name}' declares is not the one measured: check it, or give run.dt")
    return (f"the contact lasted {duration:.3g} s, {steps:.3g} steps of dt = {result.dt:.3g} s, where run.dt = "
            f"\"auto\" aims at {scene.steps_per_contact} steps of the contact time it assumed "
            f"({result.dt * scene.steps_per_contact:.3g} s or more): the rebound is under-resolved; {cause}")


SUMMARY_KEYS = ("law", "angle_deg", "speed", "en", "et", "x", "y1", "y2", "contact_duration_s", "max_overlap_m",
                "energy_ratio", "steps", "dt_s", "wall_time_s", "warnings")


def summary(result: RunResult) -> dict:
    """The stable keys of summary.json (SUMMARY_KEYS first), then extra detail."""
    scene = result.scene
    out = {"law": result.law.name}
    if scene.impact is not None:
        out.update({"angle_deg": scene.impact.angle_deg, "speed": scene.impact.speed})
        # no touch by run.end_time, or still touching then: there is no rebound to measure
        # (en = -1 would make x divide by zero; mid-contact, en -0.40 read as a result)
        measures = (rebound(result) if result.first_contact_time >= 0 and result.contacts == 0
                    else {k: None for k in ("en", "et", "x", "y1", "y2")})
    else:
        out.update({"angle_deg": None, "speed": None})
        measures = {k: None for k in ("en", "et", "x", "y1", "y2")}
        if (scene.n_particles == 2 and not scene.has_walls and result.first_contact_time >= 0
                and result.contacts == 0):
            # a two-sphere collision (with no walls, the one contact there can be): the
            # sphere-sphere counterparts of en and et
            pair = pair_rebound(result)
            measures.update({k: v for k, v in pair.items() if v is not None and math.isfinite(v)})
    out.update({k: measures[k] for k in ("en", "et", "x", "y1", "y2")})
    duration = (result.last_separation_time - result.first_contact_time
                if result.first_contact_time >= 0 and result.last_separation_time >= 0 else None)
    ratio = energy_ratio(result)
    warnings = [w for w in (incomplete_contact(result), _impact_energy_warning(result, ratio, duration),
                            energy_budget_warning(result), resolution_warning(result, duration)) if w]
    out.update({
        "contact_duration_s": duration,
        "max_overlap_m": result.max_overlap if result.contact_statistics else None,
        "energy_ratio": ratio,
        "steps": result.steps,
        "dt_s": result.dt,
        "wall_time_s": result.wall_time,
        "warnings": warnings,
        "peak_normal_force_n": result.peak_normal_force if result.contact_statistics else None,
        "peak_tangential_force_n": result.peak_tangential_force if result.contact_statistics else None,
        "particles": scene.n_particles,
        "contacts_at_end": result.contacts,
        "kinetic_energy_j": kinetic_energy(scene.mass, scene.inertia, result.velocity, result.angular_velocity),
        "peak_kinetic_energy_j": float(result.energy[:, 1].max()) if result.energy is not None else None,
        "sampled_max_overlap_m": result.sampled_max_overlap,
        "sampled_max_overlap_ratio": result.sampled_max_overlap_ratio,
        "free_flight_steps": result.flown_steps,
        "neighbour_builds": result.neighbour_builds,
        "threads": result.threads,
        "separated": result.separated,
        "dt_reason": result.dt_reason,
        "scenario": scene.source,
        "law_parameters": scene.law_parameters,
        "law_constants": {f"{scene.materials[a].name}/{scene.materials[b].name}": c
                          for (a, b), c in result.constants.items()},
    })
    if result.first_contact_time >= 0:
        out.update(collision_measures(result))
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in out.items()}


def pair_rebound(result: RunResult, i: int = 0, j: int = 1) -> dict:
    """en and et of the collision of particles i and j, measured on their relative velocity
    v_i - v_j against the initial line of centres n (from j to i) and the initial
    tangential direction t of the relative velocity: the sphere-sphere counterparts of
    the sphere-wall en, et (eq 2), equal to them through the reduced radius and mass."""
    scene = result.scene
    n = scene.position[i] - scene.position[j]
    n = n / np.linalg.norm(n)
    before = result.initial_velocity[i] - result.initial_velocity[j]
    after = result.velocity[i] - result.velocity[j]
    tangential = before - np.dot(before, n) * n
    speed_t = float(np.linalg.norm(tangential))
    approach = -float(np.dot(before, n))
    out = {"en": float(np.dot(after, n)) / approach if approach > 0.0 else math.nan, "et": math.nan}
    if speed_t > 0.0:
        t = tangential / speed_t
        out["et"] = float(np.dot(after, t)) / speed_t
    return out


def heap_angle_deg(position, radius: float, low: float = 0.2, high: float = 0.8) -> float:
    """The angle of repose (degrees) of a heap spread along +x from its highest point, from
    the final particle positions: the free surface is the highest sphere top in each
    column of width one diameter along x; the angle is that of the least-squares line
    through the surface points downstream of the summit whose height lies between
    ``low`` and ``high`` of the summit's (the flat top and the foot's loose spheres left
    out). NaN when fewer than three surface points are on the slope."""
    position = np.asarray(position, dtype=np.float64)
    x, top = position[:, 0], position[:, 2] + radius
    column = np.floor((x - x.min()) / (2.0 * radius)).astype(np.int64)
    surface_x, surface_z = [], []
    for c in np.unique(column):
        inside = column == c
        highest = np.argmax(np.where(inside, top, -np.inf))
        surface_x.append(x[highest])
        surface_z.append(top[highest])
    surface_x, surface_z = np.array(surface_x), np.array(surface_z)
    summit = int(np.argmax(surface_z))
    height = surface_z[summit]
    slope = (surface_x > surface_x[summit]) & (surface_z > low * height) & (surface_z < high * height)
    if slope.sum() < 3:
        return math.nan
    gradient = np.polyfit(surface_x[slope], surface_z[slope], 1)[0]
    return math.degrees(math.atan(-gradient))


# ---------------------------------------------------------------------------------
# Chung & Ooi (2011) measures: one sphere on its [impact] wall, or two spheres
# ---------------------------------------------------------------------------------
def collision_frame(scene, velocity, angular_velocity):
    """(n, t, partner) of the collision of particle 0: n the unit normal pointing to
    particle 0 (the [impact] wall's normal, or the line of centres from particle 1),
    t the unit tangent and partner 1 (None for the wall). For an impact t is the
    impact's tangent; for two spheres it is the direction of the initial tangential
    relative velocity of the centres, else of the initial slip of the contact point
    (spin alone), else any direction normal to n. None when the scene is neither."""
    if scene.impact is not None:
        return scene.impact.normal, scene.impact.tangent, None
    if scene.n_particles != 2 or scene.has_walls:
        return None
    n = scene.position[0] - scene.position[1]
    n = n / np.linalg.norm(n)
    relative = velocity[0] - velocity[1]
    slip = (relative + np.cross(angular_velocity[0], -scene.radius[0] * n)
            - np.cross(angular_velocity[1], scene.radius[1] * n))
    for candidate in (relative, slip, np.eye(3)[int(np.argmin(np.abs(n)))]):
        tangential = candidate - np.dot(candidate, n) * n
        if np.linalg.norm(tangential) > 1e-12 * max(float(np.linalg.norm(candidate)), 1e-300):
            return n, tangential / np.linalg.norm(tangential), 1
    raise AssertionError("no tangent for a unit normal")


def rigid_body_impact(mass, inertia, radius, velocity, angular_velocity, normal, restitution, friction):
    """Rigid-body impulse theory of a sphere collision with Coulomb friction (the
    limits of Chung & Ooi 2011 tests 4-8; Maw, Barber & Fawcett 1976 without the
    elastic tangential compliance). Arrays hold body 0 and, when their length is 2,
    body 1; a wall is body 1 absent (infinite mass, at rest). ``normal`` points from
    body 1 (or the wall) to body 0.

    The normal impulse is Pn = (1 + e) m_n |u_n| with 1/m_n = 1/m0 + 1/m1 and u the
    relative velocity of the contact points. A tangential impulse P changes the
    tangential slip by P/m_t, 1/m_t = sum over bodies of 1/m + R^2/I (7/(2m) for a
    solid sphere on a wall). If stopping the slip needs no more than mu Pn the contact
    ends rolling (P = m_t |u_t|), else it slides throughout (P = mu Pn): then
    delta v_t = mu (1 + e) v_n and delta omega = 5/2 mu (1 + e) v_n / R on a wall.
    Returns (velocity, angular_velocity, sliding) after the impact."""
    velocity = np.array(velocity, dtype=np.float64).reshape(-1, 3).copy()
    spin = np.array(angular_velocity, dtype=np.float64).reshape(-1, 3).copy()
    bodies = velocity.shape[0]
    n = np.asarray(normal, dtype=np.float64)
    arm = [-radius[0] * n] + ([radius[1] * n] if bodies > 1 else [])
    contact = [velocity[b] + np.cross(spin[b], arm[b]) for b in range(bodies)]
    u = contact[0] - (contact[1] if bodies > 1 else 0.0)
    u_n = float(u @ n)
    u_t = u - u_n * n
    inverse_normal = sum(1.0 / mass[b] for b in range(bodies))
    inverse_tangential = sum(1.0 / mass[b] + radius[b] ** 2 / inertia[b] for b in range(bodies))
    normal_impulse = (1.0 + restitution) * max(-u_n, 0.0) / inverse_normal
    slip = float(np.linalg.norm(u_t))
    stick = slip / inverse_tangential
    sliding = stick > friction * normal_impulse
    tangential = min(stick, friction * normal_impulse)
    impulse = normal_impulse * n - (tangential * u_t / slip if slip > 0.0 else 0.0)
    for b, sign in zip(range(bodies), (1.0, -1.0)):
        velocity[b] += sign * impulse / mass[b]
        spin[b] += sign * np.cross(arm[b], impulse) / inertia[b]
    return velocity, spin, bool(sliding)


def collision_measures(result: RunResult) -> dict:
    """Particle 0's rebound in the collision frame (collision_frame), beside the
    rigid-body impulse theory (rigid_body_impact) with the law's restitution and
    friction, and the closed-form Hertz limits of the elastic normal impact
    (hertz_impact): the quantities Chung & Ooi (2011) tabulate and plot. Velocities are
    of particle 0 relative to its partner's initial velocity, spin is about n x t (the
    sense of [impact].spin); ``recoil_ratio`` is the tangential slip velocity of the
    contact point over the normal speed after the impact (their V'st/V'cn).
    Empty for scenes that are not one collision."""
    scene = result.scene
    frame = collision_frame(scene, result.initial_velocity, result.initial_angular_velocity)
    if frame is None:
        return {}
    n, t, partner = frame
    bodies = [0] if partner is None else [0, partner]
    axis = np.cross(n, t)
    params = scene.law_parameters
    restitution = float(params.get("restitution", 1.0) or 1.0)
    friction = float(params.get("friction", 0.0) or 0.0)
    radius = scene.radius[bodies]
    theory_v, theory_w, sliding = rigid_body_impact(scene.mass[bodies], scene.inertia[bodies], radius,
                                                   result.initial_velocity[bodies],
                                                   result.initial_angular_velocity[bodies], n, restitution,
                                                   friction)
    reference = result.initial_velocity[partner] if partner is not None else np.zeros(3)

    def measures(velocity, spin, prefix):
        relative = velocity[0] - (velocity[1] if partner is not None else 0.0)
        slip = relative + np.cross(spin[0], -radius[0] * n) - (
            np.cross(spin[1], radius[1] * n) if partner is not None else 0.0)
        normal_out = float(relative @ n)
        return {
            f"{prefix}tangential_velocity_m_s": float((velocity[0] - reference) @ t),
            f"{prefix}spin_rad_s": float(spin[0] @ axis),
            f"{prefix}rebound_angle_deg": math.degrees(math.atan2(float(relative @ t), normal_out)),
            f"{prefix}recoil_ratio": float(slip @ t) / normal_out if normal_out > 0.0 else math.nan,
        }

    out = measures(result.velocity[bodies], result.angular_velocity[bodies], "")
    out.update(measures(theory_v, theory_w, "rigid_"))
    out["rigid_sliding"] = sliding
    out.update(hertz_impact(scene, result.initial_velocity, n, partner))
    return out


def hertz_impact(scene, velocity, normal, partner) -> dict:
    """Closed-form elastic Hertz normal impact of particle 0 on its partner (or wall) at
    the initial normal approach speed v (Chung & Ooi 2011, tests 1-3; Johnson 1985):
    alpha_max = (15 m* v^2 / (16 E* sqrt(R*)))^(2/5), F_max = 4/3 E* sqrt(R*)
    alpha_max^(3/2), t_c = 2.868 (m*^2 / (R* E*^2 v))^(1/5)."""
    from minidem.contact.laws import ContactPair

    materials = scene.materials
    first = materials[scene.particle_material[0]]
    if partner is None:
        other = materials[scene.wall_material[scene.impact.wall]]
        r_star, m_star = float(scene.radius[0]), float(scene.mass[0])
        speed = -float(velocity[0] @ normal)
    else:
        other = materials[scene.particle_material[partner]]
        r0, r1, m0, m1 = scene.radius[0], scene.radius[partner], scene.mass[0], scene.mass[partner]
        r_star, m_star = float(r0 * r1 / (r0 + r1)), float(m0 * m1 / (m0 + m1))
        speed = -float((velocity[0] - velocity[partner]) @ normal)
    if speed <= 0.0:
        return {}
    e_star = ContactPair.from_materials(first, other, r_star, m_star).effective_modulus
    overlap = (15.0 * m_star * speed**2 / (16.0 * e_star * math.sqrt(r_star))) ** 0.4
    # t_c = 2 (alpha_max / v) int_0^1 dx / sqrt(1 - x^(5/2)) = (4/5) B(2/5, 1/2) alpha_max / v,
    # exact (eq 13's 2.868 is this rounded)
    beta = math.gamma(0.4) * math.gamma(0.5) / math.gamma(0.9)
    return {"hertz_max_overlap_m": overlap,
            "hertz_peak_force_n": 4.0 / 3.0 * e_star * math.sqrt(r_star) * overlap**1.5,
            "hertz_contact_time_s": 0.8 * beta * overlap / speed}
