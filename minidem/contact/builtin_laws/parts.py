"""minidem's built-in contact-model parts (normal, damping, tangential).

Each part is one declaration and one compiled function with the signature of its kind
(``minidem.contact.declarations.PART_ARGUMENTS``). The paper's laws (``hertz.py``, ``linear.py``) are
the same physics written as single laws; two combinations reproduce two of them:

    hooke + viscous + linear_history   = ls  (bit for bit: the same operations in order)
    hertz + tsuji + mindlin            = hm  (to round-off: the dashpot coefficient is
                                              computed from the tangent stiffness kn the
                                              normal part passes on, sqrt(m* kn / 1.5),
                                              instead of hm's sqrt(m* 4/3 E* a),
                                              a = sqrt(R* d); the normal and tangential
                                              stiffnesses differ by round-off too)
"""

import math

import numba

from minidem.contact.builtin_laws.common import (
    FRICTION,
    RESTITUTION,
    hertz_damping_factor,
    incremental_spring,
    linear_damping_ratio,
)
from minidem.contact.builtin_laws.hertz import _step_mean_sqrt
from minidem.contact.builtin_laws.linear import (
    CALIBRATION_SPEED,
    NORMAL_STIFFNESS,
    STIFFNESS_RATIO,
    TANGENTIAL_STIFFNESS,
    linear_normal_stiffness,
)
from minidem.contact.declarations import ContactPart, HistorySlot, hertz_contact_time

PAPER = "Thornton, Cummins & Cleary (2011)"


# -- normal ---------------------------------------------------------------------------
@numba.njit(cache=True, inline="always")
def hooke_normal(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment, history):
    """Fn = kn d (eq 25); contact radius sqrt(R* d), the geometric one."""
    stiffness = constants[0]
    return stiffness * normal_overlap, stiffness, math.sqrt(effective_radius * normal_overlap)


HOOKE = ContactPart(
    name="hooke",
    kind="normal",
    description="linear spring Fn = kn d (eq 25); kn given or calibrated to the Hertz contact time (eq 28)",
    parameters=(NORMAL_STIFFNESS, CALIBRATION_SPEED),
    constants=("normal_stiffness",),
    history=(),
    prepare=lambda pair, params, prepared: {"normal_stiffness": linear_normal_stiffness(pair, params, "part 'hooke'")},
    function=hooke_normal,
    energy=("store",),
    provides=("linear",),
    contact_time=lambda pair, c, radius, mass, speed: math.pi * math.sqrt(mass / c["normal_stiffness"]),
    stiffness=lambda pair, c, radius, mass, overlap: c["normal_stiffness"],
    reference=f"{PAPER} section 3.2, eqs 25-28",
)


@numba.njit(cache=True, inline="always")
def hertz_normal(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment, history):
    """Fn = 4/3 E* sqrt(R*) d^1.5 (eq 15), tangent stiffness dFn/dd = 2 E* a, a = sqrt(R* d)."""
    stiffness = constants[0] * math.sqrt(effective_radius)
    root = math.sqrt(normal_overlap)
    return stiffness * normal_overlap * root, 1.5 * stiffness * root, math.sqrt(effective_radius * normal_overlap)


HERTZ = ContactPart(
    name="hertz",
    kind="normal",
    description="Hertz Fn = 4/3 E* sqrt(R*) d^1.5 (eq 15), from the materials' E and nu",
    parameters=(),
    constants=("hertz_prefactor",),
    history=(),
    prepare=lambda pair, params, prepared: {"hertz_prefactor": 4.0 / 3.0 * pair.effective_modulus},
    function=hertz_normal,
    energy=("store",),
    provides=("hertzian",),
    contact_time=lambda pair, c, radius, mass, speed: hertz_contact_time(pair.effective_modulus, radius, mass, speed),
    stiffness=lambda pair, c, radius, mass, overlap: 2.0 * pair.effective_modulus * math.sqrt(radius * overlap),
    reference=f"{PAPER} section 3.1, eq 15; Hertz (1882)",
)


# -- damping --------------------------------------------------------------------------
@numba.njit(cache=True, inline="always")
def viscous_damping(constants, effective_radius, effective_mass, normal_overlap, normal_velocity, normal_stiffness,
                    elastic_normal_force):
    """2 zeta sqrt(m* kn) d': restitution exp(-zeta pi / sqrt(1 - zeta^2)) exactly for a
    linear spring released at zero overlap (the force not clipped)."""
    return 2.0 * constants[0] * math.sqrt(effective_mass * normal_stiffness) * normal_velocity


VISCOUS = ContactPart(
    name="viscous",
    kind="damping",
    description="linear dashpot 2 zeta sqrt(m* kn) d', zeta mapped exactly from the restitution of a linear spring",
    parameters=(RESTITUTION,),
    constants=("damping_ratio",),
    history=(),
    prepare=lambda pair, params, prepared: {"damping_ratio": linear_damping_ratio(params["restitution"])},
    function=viscous_damping,
    energy=("dissipate",),
    requires=("linear",),
    stiffness=lambda pair, c, radius, mass, overlap: c["damping_ratio"],
    reference="Cundall & Strack (1979); restitution of the linear spring-dashpot, e.g. Schwager & Poschel (2007)",
)


@numba.njit(cache=True, inline="always")
def tsuji_damping(constants, effective_radius, effective_mass, normal_overlap, normal_velocity, normal_stiffness,
                  elastic_normal_force):
    """alpha sqrt(m* K) d^(1/4) d' (Tsuji et al. 1992), K = 4/3 E* sqrt(R*): with the
    Hertz tangent stiffness kn = 3/2 K d^(1/2), K d^(1/2) = kn / 1.5."""
    return constants[0] * math.sqrt(effective_mass * normal_stiffness / 1.5) * normal_velocity


TSUJI = ContactPart(
    name="tsuji",
    kind="damping",
    description="Tsuji dashpot alpha sqrt(m* K) d^1/4 d', alpha mapped from the restitution (any speed)",
    parameters=(RESTITUTION,),
    constants=("damping_factor",),
    history=(),
    prepare=lambda pair, params, prepared: {"damping_factor": hertz_damping_factor(params["restitution"])},
    function=tsuji_damping,
    energy=("dissipate",),
    requires=("hertzian",),
    # the damping ratio against the tangent stiffness is the same at every overlap
    stiffness=lambda pair, c, radius, mass, overlap: c["damping_factor"] / (2.0 * math.sqrt(1.5)),
    reference="Tsuji, Tanaka & Ishida (1992), Powder Technol. 71, 239-250",
)


# -- tangential -----------------------------------------------------------------------
_FORCE_SLOT = (HistorySlot("tangential_force", "spring force in the tangent plane (N)", vector=True, exchange=-1),)


def _prepare_linear_history(pair, params, prepared):
    stiffness = params["tangential_stiffness"]
    if stiffness is None:
        normal_stiffness = prepared["normal"].get("normal_stiffness")
        if normal_stiffness is None:
            raise ValueError("part 'linear_history' needs 'tangential_stiffness' with a normal part whose "
                             "stiffness is not constant (it takes kt = stiffness_ratio * kn otherwise)")
        ratio = params["stiffness_ratio"] if params["stiffness_ratio"] is not None else pair.stiffness_ratio
        stiffness = ratio * normal_stiffness
    return {"tangential_stiffness": stiffness, "friction": params["friction"]}


@numba.njit(cache=True, inline="always")
def linear_history_tangential(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                              contact_radius, elastic_normal_force, normal_force, tangential_increment,
                              tangential_velocity, history):
    """Ft += kt dd, capped at mu max(Fn, 0) (eq 26)."""
    return incremental_spring(history, constants[0], tangential_increment, constants[1] * max(normal_force, 0.0))


LINEAR_HISTORY = ContactPart(
    name="linear_history",
    kind="tangential",
    description="incremental spring Ft += kt dd capped at mu Fn (eq 26); kt given or kappa kn of a linear normal",
    parameters=(FRICTION, TANGENTIAL_STIFFNESS, STIFFNESS_RATIO),
    constants=("tangential_stiffness", "friction"),
    history=_FORCE_SLOT,
    prepare=_prepare_linear_history,
    function=linear_history_tangential,
    energy=("store", "dissipate"),
    stiffness=lambda pair, c, radius, mass, overlap: c["tangential_stiffness"],
    reference=f"{PAPER} section 3.2, eq 26; Cundall & Strack (1979)",
)


def prepare_shear_and_friction(pair, params, prepared):
    """8 G* (Mindlin's kt = 8 G* a) and mu: the constants of mindlin and of marshall twisting."""
    return {"mindlin_prefactor": 8.0 * pair.effective_shear_modulus, "friction": params["friction"]}


@numba.njit(cache=True, inline="always")
def mindlin_tangential(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                       contact_radius, elastic_normal_force, normal_force, tangential_increment, tangential_velocity,
                       history):
    """Ft += 8 G* a dd capped at mu max(Fn, 0) (eq 39), a = sqrt(R* d) averaged over the
    step as hm does (the end-of-step radius makes the update first order in dt)."""
    stiffness = constants[0] * math.sqrt(effective_radius) * _step_mean_sqrt(
        normal_overlap - normal_overlap_increment, normal_overlap)
    return incremental_spring(history, stiffness, tangential_increment, constants[1] * max(normal_force, 0.0))


MINDLIN = ContactPart(
    name="mindlin",
    kind="tangential",
    description="Mindlin no-slip, incremental Ft += 8 G* a dd capped at mu Fn (eq 39); needs a Hertzian normal",
    parameters=(FRICTION,),
    constants=("mindlin_prefactor", "friction"),
    history=_FORCE_SLOT,
    prepare=prepare_shear_and_friction,
    function=mindlin_tangential,
    energy=("store", "dissipate"),
    requires=("hertzian",),
    stiffness=lambda pair, c, radius, mass, overlap: c["mindlin_prefactor"] * math.sqrt(radius * overlap),
    reference=f"{PAPER} section 3.3, eq 39; Mindlin (1949)",
)

PARTS = [HOOKE, HERTZ, VISCOUS, TSUJI, LINEAR_HISTORY, MINDLIN]
