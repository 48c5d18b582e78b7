"""The Walton-Braun linear hysteretic contact law.

O.R. Walton and R.L. Braun, "Viscosity, granular-temperature, and stress calculations
for shearing assemblies of inelastic, frictional disks", J. Rheol. 30 (1986) 949-980.

Normal force (partially latching spring). With delta the overlap and delta_max the
largest overlap reached so far in this contact:

    loading      Fn = k1 delta                                   (delta = delta_max)
    unloading    Fn = k2 (delta - delta_0),  delta_0 = delta_max (1 - k1/k2)
    reloading    along the unloading line until it meets k1 delta at delta_max,
                 then on the loading line again

Both branches are the single expression Fn = max(k1 delta_max + k2 (delta - delta_max), 0):
on first loading delta = delta_max and it is k1 delta. The energy lost in a normal
impact is the area between the branches, so the coefficient of restitution is
e = sqrt(k1 / k2) at any impact speed: k2 = k1 / e^2. Below delta_0 the force is zero
although the bodies still overlap geometrically (the "plastic" dent); the contact and
its history end when the overlap does.

Tangential force: an incremental linear spring Ft += kt dd, truncated at the Coulomb
limit mu Fn (the same rule as the paper's LS law, Thornton et al. 2011 eq 26). It is
kept as a vector history slot, which minidem carries into the current tangent plane.

Choosing k1: give ``loading_stiffness``, or leave it out and minidem calibrates it like
the LS law of Thornton, Cummins & Cleary (2011) eq 28: the loading branch then reaches
maximum overlap in the same time as a Hertz impact at the calibration speed,
k1 = m* pi^2 / tc_Hertz^2.
"""

import math

import numba

from minidem.contact.builtin_laws.common import FRICTION, incremental_spring
from minidem.contact import ContactLaw, HistorySlot, Parameter, hertz_contact_time

# indices into the constants row (the order of WALTON_BRAUN.constants)
K1, K2, KT, MU = 0, 1, 2, 3
# history layout: the tangential force vector first (incremental_spring uses slots 0-2)
TANGENTIAL_FORCE, MAX_OVERLAP = 0, 3


def prepare(pair, params):
    """Material pair + parameters -> the constants the force function reads."""
    loading_stiffness = params["loading_stiffness"]
    if loading_stiffness is None:
        speed = params["calibration_speed"] or pair.reference_speed
        if not speed:
            raise ValueError("give contact.loading_stiffness, or a speed to calibrate it from the Hertz "
                             "contact time: contact.calibration_speed or an [impact] block")
        tc = hertz_contact_time(pair.effective_modulus, pair.reference_radius, pair.reference_mass, speed)
        loading_stiffness = pair.reference_mass * math.pi**2 / tc**2
    kappa = params["stiffness_ratio"]
    if kappa is None:
        kappa = pair.stiffness_ratio  # 2(1-nu)/(2-nu) for like materials (Thornton et al. eq 10)
    return {
        "loading_stiffness": loading_stiffness,
        "unloading_stiffness": loading_stiffness / params["restitution"] ** 2,
        "tangential_stiffness": params["tangential_stiffness"] or kappa * loading_stiffness,
        "friction": params["friction"],
    }


def contact_time(pair, constants, effective_radius, effective_mass, normal_speed):
    """Duration of the force pulse of a normal impact: a quarter period on each branch,
    pi/2 (sqrt(m*/k1) + sqrt(m*/k2)), independent of the speed."""
    return 0.5 * math.pi * (math.sqrt(effective_mass / constants["loading_stiffness"])
                            + math.sqrt(effective_mass / constants["unloading_stiffness"]))


# cache=True is optional: minidem caches the kernel this is compiled into, keyed on this
# function and everything it calls
@numba.njit
def walton_braun_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                       normal_velocity, tangential_increment, tangential_velocity, history):
    max_overlap = max(history[MAX_OVERLAP], normal_overlap)
    history[MAX_OVERLAP] = max_overlap
    # the unloading line through (delta_max, k1 delta_max): the loading line while delta = delta_max
    normal_force = max(constants[K1] * max_overlap + constants[K2] * (normal_overlap - max_overlap), 0.0)
    ftx, fty, ftz = incremental_spring(history, constants[KT], tangential_increment, constants[MU] * normal_force)
    return normal_force, ftx, fty, ftz


WALTON_BRAUN = ContactLaw(
    name="walton_braun",
    description="Walton-Braun linear hysteretic normal law (k1 loading, k2 = k1/e^2 unloading) with an "
                "incremental tangential spring capped at mu Fn",
    parameters=(
        FRICTION,
        Parameter("restitution", None, "-", "normal coefficient of restitution e = sqrt(k1/k2)",
                  low=0.0, high=1.0, low_open=True, required=True),
        Parameter("loading_stiffness", None, "N/m", "k1; when absent, calibrated so that loading lasts as "
                  "long as in a Hertz impact (Thornton et al. 2011 eq 28)", low=0.0, low_open=True),
        Parameter("calibration_speed", None, "m/s", "normal speed for the k1 calibration; when absent, "
                  "the [impact] speed", low=0.0, low_open=True),
        Parameter("tangential_stiffness", None, "N/m", "kt; when absent, stiffness_ratio * k1",
                  low=0.0, low_open=True),
        Parameter("stiffness_ratio", None, "-", "kt/k1; when absent, 2(1-nu)/(2-nu) from the materials",
                  low=0.0, low_open=True),
    ),
    constants=("loading_stiffness", "unloading_stiffness", "tangential_stiffness", "friction"),
    history=(
        HistorySlot("tangential_force", "spring force in the tangent plane (N)", vector=True, exchange=-1),
        HistorySlot("max_overlap", "largest overlap reached in this contact, delta_max (m)", exchange=1),
    ),
    prepare=prepare,
    force=walton_braun_force,
    contact_time=contact_time,
    aliases=("wb", "linear_hysteretic"),
    reference="Walton & Braun, J. Rheol. 30 (1986) 949",
)
