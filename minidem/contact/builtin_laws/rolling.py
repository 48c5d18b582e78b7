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
from minidem.contact.declarations import ContactPart, HistorySlot, Parameter

AI = "Ai, Chen, Rotter & Ooi (2011), Powder Technol. 206, 269-282"
ROLLING_FRICTION = Parameter("rolling_friction", None, "-", "coefficient of rolling resistance mu_r: the "
                             "rolling couple is at most mu_r R* Fn", low=0.0, required=True)


# -- rolling ---------------------------------------------------------------------------
@numba.njit(cache=True, inline="always")
def constant_torque_rolling(constants, effective_radius, effective_mass, rolling_inertia, normal_overlap,
                            contact_radius, normal_stiffness, normal_force, rolling_increment, rolling_velocity,
                            history):
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
def epsd_rolling(constants, effective_radius, effective_mass, rolling_inertia, normal_overlap, contact_radius,
                 normal_stiffness, normal_force, rolling_increment, rolling_velocity, history):
    """Elastic-plastic spring-dashpot (Ai et al. model C): a spring couple
    M_k += -k_r w_r dt, k_r = 2.25 kn mu_r^2 R*^2, capped at mu_r R* Fn (the plastic
    limit), plus a dashpot -eta_r 2 sqrt(I_r k_r) w_r while below the limit, I_r the
    pair's moment of inertia for relative rolling about the contact point:
    1/I_r = 1/(I_i + m_i r_i^2) + 1/(I_j + m_j r_j^2), 7/5 m r^2 for a sphere at a wall."""
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
    damping = eta_r * 2.0 * math.sqrt(rolling_inertia * stiffness)
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
    history=(HistorySlot("rolling_moment", "the spring's couple on the first body (N m)", vector=True,
                         exchange=-1),),
    prepare=lambda pair, params, prepared: {"rolling_friction": params["rolling_friction"],
                                            "rolling_damping": params["rolling_damping"]},
    function=epsd_rolling,
    energy=("store", "dissipate"),
    reference=f"{AI}, model C (EPSD)",
)


LAMMPS = "LAMMPS GRANULAR pair style (Thompson et al. 2022, Comput. Phys. Commun. 271, 108171)"


@numba.njit(cache=True, inline="always")
def sds_rolling(constants, effective_radius, effective_mass, rolling_inertia, normal_overlap, contact_radius,
                normal_stiffness, normal_force, rolling_increment, rolling_velocity, history):
    """Spring-dashpot-slider (LAMMPS' rolling sds, Luding 2008): a rolling "force"
    F_r = -k_roll xi - gamma_roll v_roll on the rolling displacement xi (the integral of
    v_roll = R* w_r x n), capped as a whole at mu_r Fn, and the couple R* n x F_r. In
    couple form, M = -k_roll R*^2 theta_r - gamma_roll R*^2 w_r with |M| <= mu_r R* Fn,
    theta_r the rolling rotation; at the cap the spring is reset to M + gamma_roll R*^2 w_r
    (the dashpot part of the capped couple is not stored)."""
    radius2 = effective_radius * effective_radius
    stiffness, viscosity = constants[0] * radius2, constants[1] * radius2
    limit = constants[2] * effective_radius * max(normal_force, 0.0)
    sx = history[0] - stiffness * rolling_increment[0]
    sy = history[1] - stiffness * rolling_increment[1]
    sz = history[2] - stiffness * rolling_increment[2]
    mx = sx - viscosity * rolling_velocity[0]
    my = sy - viscosity * rolling_velocity[1]
    mz = sz - viscosity * rolling_velocity[2]
    mx, my, mz, full = coulomb_cap(mx, my, mz, limit)
    if full:  # the spring takes what the capped couple leaves after the dashpot
        sx = mx + viscosity * rolling_velocity[0]
        sy = my + viscosity * rolling_velocity[1]
        sz = mz + viscosity * rolling_velocity[2]
    history[0], history[1], history[2] = sx, sy, sz
    return mx, my, mz


SDS_ROLLING_CONSTANTS = ("rolling_stiffness", "rolling_viscosity", "rolling_friction")  # its parameters as given
SDS_ROLLING = ContactPart(
    name="sds_rolling",
    kind="rolling",
    description="spring-dashpot-slider (LAMMPS rolling sds): M = -R*^2 (k_roll theta_r + gamma_roll w_r) "
                "capped as a whole at mu_r R* Fn",
    parameters=(Parameter("rolling_stiffness", None, "N/m", "k_roll, the rolling spring on the rolling "
                          "displacement R* theta_r (couple stiffness k_roll R*^2 N m/rad)", low=0.0, required=True),
                Parameter("rolling_viscosity", 0.0, "N s/m", "gamma_roll, the rolling dashpot on R* w_r "
                          "(couple gamma_roll R*^2 w_r)", low=0.0),
                ROLLING_FRICTION),
    constants=SDS_ROLLING_CONSTANTS,
    history=(HistorySlot("rolling_spring_moment", "the spring's couple on the first body (N m)", vector=True,
                         exchange=-1),),
    prepare=lambda pair, params, prepared: {name: params[name] for name in SDS_ROLLING_CONSTANTS},
    function=sds_rolling,
    energy=("store", "dissipate"),
    reference=f"{LAMMPS}, rolling sds; Luding (2008), Granul. Matter 10, 235-246",
)


# -- twisting --------------------------------------------------------------------------
@numba.njit(cache=True, inline="always")
def sds_twisting(constants, effective_radius, effective_mass, normal_overlap, contact_radius, normal_stiffness,
                 normal_force, twisting_increment, twisting_velocity, history):
    """Spring-dashpot-slider about the normal (LAMMPS' twisting sds): M = -k_tw xi_tw -
    gamma_tw w_t on the twist angle xi_tw, capped as a whole at mu_tw Fn (mu_tw a length);
    at the cap the spring is reset to M + gamma_tw w_t."""
    stiffness, viscosity = constants[0], constants[1]
    limit = constants[2] * max(normal_force, 0.0)
    spring = history[0] - stiffness * twisting_increment
    moment = spring - viscosity * twisting_velocity
    if abs(moment) > limit:
        moment = math.copysign(limit, moment)
        spring = moment + viscosity * twisting_velocity
    history[0] = spring
    return moment


SDS_TWISTING_CONSTANTS = ("twisting_stiffness", "twisting_viscosity", "twisting_friction")  # as given
SDS_TWISTING = ContactPart(
    name="sds_twisting",
    kind="twisting",
    description="spring-dashpot-slider about the normal (LAMMPS twisting sds): M = -k_tw xi - gamma_tw w_t "
                "capped at mu_tw Fn",
    parameters=(Parameter("twisting_stiffness", None, "N m/rad", "k_tw, the twisting spring", low=0.0,
                          required=True),
                Parameter("twisting_viscosity", 0.0, "N m s/rad", "gamma_tw, the twisting dashpot", low=0.0),
                Parameter("twisting_friction", None, "m", "mu_tw: the twisting couple is at most mu_tw Fn (a "
                          "length, as LAMMPS' twisting sds; Coulomb friction over a contact disc of radius a "
                          "under uniform pressure gives 2/3 mu a)", low=0.0, required=True)),
    constants=SDS_TWISTING_CONSTANTS,
    history=(HistorySlot("twisting_spring_moment", "the spring's couple about the normal on the first body (N m)",
                         exchange=1),),
    prepare=lambda pair, params, prepared: {name: params[name] for name in SDS_TWISTING_CONSTANTS},
    function=sds_twisting,
    energy=("store", "dissipate"),
    reference=f"{LAMMPS}, twisting sds; Luding (2008), Granul. Matter 10, 235-246",
)



@numba.njit(cache=True, inline="always")
def marshall_twisting(constants, effective_radius, effective_mass, normal_overlap, contact_radius, normal_stiffness,
                      normal_force, twisting_increment, twisting_velocity, history):
    """Marshall (2009): a twisting spring M += -k_tw w_t dt, k_tw = 0.5 kt a^2 with the
    Mindlin stiffness kt = 8 G* a, capped at the torsional sliding limit 2/3 mu Fn a:
    Coulomb friction over a contact disc under uniform pressure, as Marshall and LAMMPS'
    twisting marshall take it (under the Hertz pressure the full-slip torque is
    3 pi/16 mu Fn a, Lubkin 1951, 12 % less)."""
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
    constants=("mindlin_prefactor", "friction"),
    history=(HistorySlot("twisting_moment", "the spring's couple about the normal on the first body (N m)",
                         exchange=1),),
    prepare=prepare_shear_and_friction,
    function=marshall_twisting,
    energy=("store", "dissipate"),
    requires=("hertzian",),
    reference="Marshall (2009), J. Comput. Phys. 228, 1541-1561; Deresiewicz (1954) for the 2/3 mu Fn a limit",
)

PARTS = [CONSTANT_TORQUE, EPSD, SDS_ROLLING, MARSHALL, SDS_TWISTING]
