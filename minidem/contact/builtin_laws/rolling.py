"""Rolling and twisting resistance parts: couples that oppose the relative rotation of
the two bodies in contact (the engine applies the returned couple to the first body and
its opposite to the second).

Notation: w_r the relative spin in the tangent plane (rolling), w_t the relative spin
along the normal (twisting), R* the effective radius, Fn the total normal force.
"""

import math

import numba

from minidem.contact.builtin_laws.common import FRICTION, coulomb_cap, norm3
from minidem.contact.builtin_laws.parts import prepare_shear_and_friction
from minidem.contact.laws import ContactPart, HistorySlot, Parameter

AI = "Ai, Chen, Rotter & Ooi (2011), Powder Technol. 206, 269-282"
ROLLING_FRICTION = Parameter("rolling_friction", None, "-", "coefficient of rolling resistance mu_r: the "
                             "rolling couple is at most mu_r R* Fn", low=0.0, required=True)


# -- rolling ---------------------------------------------------------------------------
@numba.njit(cache=True, inline="always")
def constant_torque_rolling(constants, effective_radius, effective_mass, normal_overlap, contact_radius,
                            normal_stiffness, normal_force, rolling_increment, rolling_velocity, history):
    """M = -mu_r R* Fn w_r / |w_r| (Ai et al. model A): constant magnitude while rolling."""
    wx, wy, wz = rolling_velocity
    spin = norm3(wx, wy, wz)
    if spin == 0.0:
        return 0.0, 0.0, 0.0
    scale = -constants[0] * effective_radius * max(normal_force, 0.0) / spin
    return scale * wx, scale * wy, scale * wz


CONSTANT_TORQUE = ContactPart(
    name="constant_torque",
    kind="rolling",
    description="constant directional torque M = -mu_r R* Fn w_r/|w_r| (Ai et al. 2011 model A); "
                "chatters about rest",
    parameters=(ROLLING_FRICTION,),
    constants=("rolling_friction",),
    history=(),
    prepare=lambda pair, params, prepared: {"rolling_friction": params["rolling_friction"]},
    function=constant_torque_rolling,
    energy=("dissipate",),
    reference=f"{AI}, model A",
)


@numba.njit(cache=True, inline="always")
def epsd_rolling(constants, effective_radius, effective_mass, normal_overlap, contact_radius, normal_stiffness,
                 normal_force, rolling_increment, rolling_velocity, history):
    """Elastic-plastic spring-dashpot (Ai et al. model C): a spring couple
    M_k += -k_r w_r dt, k_r = 2.25 kn mu_r^2 R*^2, capped at mu_r R* Fn (the plastic
    limit), plus a dashpot -eta_r 2 sqrt(I_r k_r) w_r while below the limit,
    I_r = 7/5 m* R*^2 (a sphere rolling about its contact point)."""
    mu_r, eta_r = constants[0], constants[1]
    radius = effective_radius
    stiffness = 2.25 * normal_stiffness * mu_r * mu_r * radius * radius
    limit = mu_r * radius * max(normal_force, 0.0)
    mx = history[0] - stiffness * rolling_increment[0]
    my = history[1] - stiffness * rolling_increment[1]
    mz = history[2] - stiffness * rolling_increment[2]
    mx, my, mz, full = coulomb_cap(mx, my, mz, limit)
    history[0], history[1], history[2] = mx, my, mz
    if full or eta_r == 0.0:
        return mx, my, mz
    damping = eta_r * 2.0 * math.sqrt(1.4 * effective_mass * radius * radius * stiffness)
    return (mx - damping * rolling_velocity[0], my - damping * rolling_velocity[1],
            mz - damping * rolling_velocity[2])


EPSD = ContactPart(
    name="epsd",
    kind="rolling",
    description="elastic-plastic spring-dashpot (Ai et al. 2011 model C): spring k_r = 2.25 kn mu_r^2 R*^2 "
                "capped at mu_r R* Fn, viscous eta_r below the cap; holds a sphere on slopes tan(theta) < mu_r",
    parameters=(ROLLING_FRICTION,
                Parameter("rolling_damping", 0.3, "-", "eta_r, the rolling dashpot's damping ratio (Ai et al. "
                          "recommend 0.3)", low=0.0)),
    constants=("rolling_friction", "rolling_damping"),
    history=(HistorySlot("rolling_moment", "the spring's couple on the first body (N m)", vector=True),),
    prepare=lambda pair, params, prepared: {"rolling_friction": params["rolling_friction"],
                                            "rolling_damping": params["rolling_damping"]},
    function=epsd_rolling,
    energy=("store", "dissipate"),
    reference=f"{AI}, model C (EPSD)",
)


# -- twisting --------------------------------------------------------------------------
@numba.njit(cache=True, inline="always")
def marshall_twisting(constants, effective_radius, effective_mass, normal_overlap, contact_radius, normal_stiffness,
                      normal_force, twisting_increment, twisting_velocity, history):
    """Marshall (2009): a twisting spring M += -k_tw w_t dt, k_tw = 0.5 kt a^2 with the
    Mindlin stiffness kt = 8 G* a, capped at the torsional sliding limit 2/3 mu Fn a
    (Coulomb friction over a Hertz contact disc)."""
    a = contact_radius
    stiffness = 0.5 * constants[0] * a * a * a
    limit = 2.0 / 3.0 * constants[1] * max(normal_force, 0.0) * a
    moment = history[0] - stiffness * twisting_increment
    if abs(moment) > limit:
        moment = math.copysign(limit, moment)
    history[0] = moment
    return moment


MARSHALL = ContactPart(
    name="marshall",
    kind="twisting",
    description="twisting spring k_tw = 0.5 kt a^2 (kt = 8 G* a) capped at 2/3 mu Fn a (Marshall 2009)",
    parameters=(FRICTION,),
    constants=("shear_modulus", "friction"),
    history=(HistorySlot("twisting_moment", "the spring's couple about the normal on the first body (N m)"),),
    prepare=prepare_shear_and_friction,
    function=marshall_twisting,
    energy=("store", "dissipate"),
    requires=("hertzian",),
    reference="Marshall (2009), J. Comput. Phys. 228, 1541-1561; Deresiewicz (1954) for the 2/3 mu Fn a limit",
)

PARTS = [CONSTANT_TORQUE, EPSD, MARSHALL]
