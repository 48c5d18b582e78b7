"""Rebound measures of an oblique impact (paper eqs 2 and 9) and energy balance."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the sweep's parent process reads rows without loading the engine
    from minidem.engine.simulation import RunResult


def kinetic_energy(mass, inertia, velocity, angular_velocity) -> float:
    """Translational plus rotational kinetic energy of all particles (J)."""
    from minidem.engine import integrate  # here: importing analysis must not load numba (see above)

    return float(integrate.kinetic_energy(np.ascontiguousarray(mass, dtype=np.float64),
                                          np.ascontiguousarray(inertia, dtype=np.float64),
                                          np.ascontiguousarray(velocity, dtype=np.float64),
                                          np.ascontiguousarray(angular_velocity, dtype=np.float64)))


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
# spring, 20 steps), 5e-10 at the default 2000. Ten times that, and never below 1e-6,
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
    budget = initial + max(result.gravity_work_max, 0.0)
    if peak <= budget * (1.0 + 1e-3):
        return None
    times = (f"{peak / budget:.3g} times" if budget > 0.0 else "more than")
    return (f"the kinetic energy reached {peak:.3g} J, {times} what the scene can supply ({budget:.3g} J: the "
            "initial kinetic energy plus the work of gravity; contacts cannot add energy): the time step is too "
            "large for the contacts, or the law creates energy (docs/time-step.md)")


SUMMARY_KEYS = ("law", "angle_deg", "speed", "en", "et", "x", "y1", "y2", "contact_duration_s", "max_overlap_m",
                "energy_ratio", "steps", "dt_s", "wall_time_s", "warnings")


def summary(result: RunResult) -> dict:
    """The stable keys of summary.json (SUMMARY_KEYS first), then extra detail."""
    scene = result.scene
    out = {"law": result.law.name}
    if scene.impact is not None:
        out.update({"angle_deg": scene.impact.angle_deg, "speed": scene.impact.speed})
        # no touch by run.end_time: there is no rebound to measure (and en = -1 would
        # make x divide by zero)
        measures = rebound(result) if result.first_contact_time >= 0 else {k: None for k in
                                                                            ("en", "et", "x", "y1", "y2")}
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
                            energy_budget_warning(result)) if w]
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
        "neighbour_builds": result.neighbour_builds,
        "threads": result.threads,
        "separated": result.separated,
        "dt_reason": result.dt_reason,
        "scenario": scene.source,
        "law_parameters": scene.law_parameters,
        "law_constants": {f"{scene.materials[a].name}/{scene.materials[b].name}": c
                          for (a, b), c in result.constants.items()},
    })
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
