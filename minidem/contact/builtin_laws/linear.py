"""The linear spring law of the paper (LS, section 3.2, eqs 25-28)."""

import math

import numba

from minidem.contact.builtin_laws.common import (
    FRICTION,
    RESTITUTION,
    damped_normal_force,
    incremental_spring,
    linear_damping_ratio,
)
from minidem.contact.declarations import ContactLaw, HistorySlot, Parameter, hertz_contact_time

# indices into the constants row (order of LS.constants)
KN, KT, MU, ZETA = 0, 1, 2, 3


def linear_normal_stiffness(pair, params, who="law 'ls'"):
    """kn as given, or calibrated (eqs 27-28): the stiffness whose normal-impact duration
    pi sqrt(m*/kn) equals the Hertz duration (eq 13) at the scenario's impact speed.
    Written as m* pi^2 / tc^2 rather than with the paper's rounded 1.2024 so the two
    durations agree exactly."""
    normal_stiffness = params["normal_stiffness"]
    if normal_stiffness is None:
        speed = params["calibration_speed"] or pair.reference_speed
        if not speed:
            raise ValueError(
                f"{who} needs 'normal_stiffness', or a speed to calibrate it from the "
                "Hertz contact time: set contact.calibration_speed or use an [impact] block"
            )
        tc = hertz_contact_time(pair.effective_modulus, pair.reference_radius, pair.reference_mass, speed)
        normal_stiffness = pair.reference_mass * math.pi**2 / tc**2
    return normal_stiffness


def prepare_linear(pair, params):
    normal_stiffness = linear_normal_stiffness(pair, params)
    kappa = params["stiffness_ratio"]
    if kappa is None:
        kappa = pair.stiffness_ratio  # eq 10 from the Poisson ratios
    tangential_stiffness = params["tangential_stiffness"] or kappa * normal_stiffness
    return {
        "normal_stiffness": normal_stiffness,
        "tangential_stiffness": tangential_stiffness,
        "friction": params["friction"],
        "damping_ratio": linear_damping_ratio(params["restitution"]),
    }


def linear_contact_time(pair, constants, effective_radius, effective_mass, normal_speed):
    """Half period of the undamped mass-spring system, tc = pi sqrt(m*/kn) (eq 27)."""
    return math.pi * math.sqrt(effective_mass / constants["normal_stiffness"])


def linear_stiffness(pair, constants, effective_radius, effective_mass, normal_overlap):
    """kn, kt and the dashpot's damping ratio: the spring is linear, so no overlap dependence."""
    return constants["normal_stiffness"], constants["tangential_stiffness"], constants["damping_ratio"]


NORMAL_STIFFNESS = Parameter("normal_stiffness", None, "N/m", "kn; when absent, calibrated so that a normal "
                             "impact lasts as long as the Hertz one (eq 28)", low=0.0, low_open=True)
TANGENTIAL_STIFFNESS = Parameter("tangential_stiffness", None, "N/m", "kt; when absent, stiffness_ratio * kn",
                                 low=0.0, low_open=True)
STIFFNESS_RATIO = Parameter("stiffness_ratio", None, "-", "kappa = kt/kn; when absent, 2(1-nu)/(2-nu) from "
                            "the materials (eq 10)", low=0.0, low_open=True)
CALIBRATION_SPEED = Parameter("calibration_speed", None, "m/s", "normal speed for the kn calibration; when "
                              "absent, the [impact] speed", low=0.0, low_open=True)


@numba.njit(cache=True)
def linear_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                 normal_velocity, tangential_increment, tangential_velocity, history):
    # linear dashpot 2 zeta sqrt(m* kn), the force clipped at zero (never tensile): zeta
    # is mapped from e for that clipped force (common.linear_damping_ratio)
    damping = 2.0 * constants[ZETA] * math.sqrt(effective_mass * constants[KN])
    normal_force = damped_normal_force(constants[KN] * normal_overlap, damping * normal_velocity)
    # eq 26: incremental tangential spring, truncated at the Coulomb limit
    ftx, fty, ftz = incremental_spring(history, constants[KT], tangential_increment,
                                       constants[MU] * max(normal_force, 0.0))
    return normal_force, ftx, fty, ftz


LS = ContactLaw(
    name="ls",
    description="Linear spring (LS): Fn = kn d, incremental Ft += kt dd capped at mu Fn (eqs 25-28)",
    parameters=(
        FRICTION,
        NORMAL_STIFFNESS,
        TANGENTIAL_STIFFNESS,
        STIFFNESS_RATIO,
        CALIBRATION_SPEED,
        RESTITUTION,
    ),
    constants=("normal_stiffness", "tangential_stiffness", "friction", "damping_ratio"),
    history=(HistorySlot("tangential_force", "spring force in the tangent plane (N)", vector=True, exchange=-1),),
    prepare=prepare_linear,
    force=linear_force,
    contact_time=linear_contact_time,
    stiffness=linear_stiffness,
    aliases=("linear_spring", "lsd"),
    normal_part="hooke",  # its first constant is the hooke part's kn
    reference="Thornton, Cummins & Cleary (2011) section 3.2",
)

LAWS = [LS]
