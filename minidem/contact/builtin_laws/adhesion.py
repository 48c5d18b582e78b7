"""Adhesive normal parts: JKR, DMT and the simplified JKR of LIGGGHTS (sjkr).

Notation: d the normal overlap (negative while the surfaces are apart), R* the effective
radius, E* the effective modulus, gamma the work of adhesion per unit area (J/m^2; the
``surface_energy`` parameter), a the contact radius.

* JKR (Johnson, Kendall & Roberts 1971; Johnson 1985, section 5.5):
      d = a^2 / R* - sqrt(2 pi gamma a / E*),   Fn = 4 E* a^3 / (3 R*) - sqrt(8 pi gamma E* a^3)
  The contact forms at touch (d = 0, where Fn jumps to -8/9 Fc), follows that curve into
  tension on unloading and breaks at the critical separation
      d_c = -3/4 (pi^2 gamma^2 R* / E*^2)^(1/3)   (a^3 = pi gamma R*^2 / (8 E*), Fn = -5/9 Fc)
  passing through the pull-off force Fc = 3/2 pi gamma R* (a^3 = 9 pi gamma R*^2 / (8 E*)).
  The hysteresis (formed at touch, broken at d_c) dissipates the work of separation
      W_s = 0.663 pi gamma a_z^2,  a_z^3 = 2 pi gamma R*^2 / E*  (a at d = 0),
  the integral of -Fn from d_c to 0; a sphere hitting a wall elastically sticks when its
  kinetic energy is below W_s (Thornton & Ning 1998): v_c = sqrt(2 W_s / m*); for a
  sphere of density rho on a wall their V_s = 1.84 (gamma^5 / (rho^3 E*^2 R^5))^(1/6)
  (docs/laws.md: why the form quoted with the pull-off force and 1.84 is not the same).
* DMT (Derjaguin, Muller & Toporov 1975; as LAMMPS' granular dmt):
      Fn = 4/3 E* sqrt(R*) d^1.5 - 2 pi gamma R*   while d > 0,
  formed and broken at touch; pull-off force 2 pi gamma R*.
* sjkr (LIGGGHTS' ``cohesion sjkr``, simplified JKR): Hertz plus a cohesive force k A
  while overlapping, k the cohesion energy density (J/m^3) and A the area of the overlap
  lens of the undeformed surfaces, A = pi a_g^2 with a_g^2 = 2 R* d to first order in d/R:
      Fn = 4/3 E* sqrt(R*) d^1.5 - 2 pi k R* d   while d > 0.
  LIGGGHTS evaluates the lens from the two radii (sphere-wall pi (2 R d - d^2)); the parts
  see R* and d only, so minidem keeps the leading term, the same for every pair of radii
  (relative difference d / 2R for a wall). With K = 4/3 E* sqrt(R*) and c = 2 pi k R*:
  the largest tension, at d* = (2c / 3K)^2, is 4 c^3 / (27 K^2); the attraction wins up to
  d0 = (c / K)^2, and the well is c d0^2 / 10 deep.
"""

import math

import numba

from minidem.contact.builtin_laws.parts import HERTZ, hertz_normal
from minidem.contact.declarations import ContactPart, HistorySlot, Parameter

SURFACE_ENERGY = Parameter(
    "surface_energy", None, "J/m^2", "work of adhesion gamma per unit contact area (JKR pull-off "
    "3/2 pi gamma R*, DMT 2 pi gamma R*); per material pair through [contact.pairs]", low=0.0, required=True)
JKR_REFERENCE = ("Johnson, Kendall & Roberts (1971), Proc. R. Soc. A 324, 301-313; Thornton & Ning (1998), "
                 "Powder Technol. 99, 154-162")
DMT_REFERENCE = "Derjaguin, Muller & Toporov (1975), J. Colloid Interface Sci. 53, 314-326"


@numba.njit(cache=True, inline="always")
def jkr_critical_separation(effective_modulus, surface_energy, effective_radius):
    """|d_c| = 3/4 (pi^2 gamma^2 R* / E*^2)^(1/3), where the JKR curve ends (m)."""
    return 0.75 * (math.pi * math.pi * surface_energy * surface_energy * effective_radius
                   / (effective_modulus * effective_modulus)) ** (1.0 / 3.0)


@numba.njit(cache=True, inline="always")
def jkr_contact_radius(effective_modulus, surface_energy, effective_radius, normal_overlap):
    """The contact radius a of the stable JKR branch at overlap d >= d_c.

    With s = sqrt(a): f(s) = s^4 / R* - c s - d = 0, c = sqrt(2 pi gamma / E*). f is convex
    for s > 0, so Newton's method started right of the root converges to it monotonically
    from above (never onto the unstable branch s < s_c). The start s0 = (c R*)^(1/3) +
    (R* max(d, 0))^(1/4) has f(s0) >= 0 (f((c R*)^(1/3)) = -d, and the quartic grows faster
    than the linear term past it). Quadratic convergence except at d_c itself (a double
    root), where 100 steps still give a to ~1e-10 relative."""
    c = math.sqrt(2.0 * math.pi * surface_energy / effective_modulus)
    s = (c * effective_radius) ** (1.0 / 3.0) + math.sqrt(math.sqrt(effective_radius * max(normal_overlap, 0.0)))
    for _ in range(100):
        s3 = s * s * s
        f = s3 * s / effective_radius - c * s - normal_overlap
        slope = 4.0 * s3 / effective_radius - c
        if f <= 0.0 or slope <= 0.0:
            break
        step = f / slope
        s -= step
        if step <= 1e-15 * s:
            break
    return s * s


@numba.njit(cache=True, inline="always")
def jkr_normal(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment, history):
    """JKR with its hysteresis (module docstring). history[0] = 1 while in contact: set at
    touch, cleared past the critical separation; apart and not formed, no force. The
    stiffness passed on (to damping) is 2 E* a, Hertz's at the JKR contact radius (as
    LAMMPS' jkr damping uses a)."""
    effective_modulus, surface_energy = constants[0], constants[1]
    if normal_overlap >= 0.0:
        history[0] = 1.0
    elif history[0] == 0.0 or normal_overlap < -jkr_critical_separation(effective_modulus, surface_energy,
                                                                         effective_radius):
        history[0] = 0.0
        return 0.0, 0.0, 0.0
    a = jkr_contact_radius(effective_modulus, surface_energy, effective_radius, normal_overlap)
    a3 = a * a * a
    force = (4.0 * effective_modulus * a3 / (3.0 * effective_radius)
             - math.sqrt(8.0 * math.pi * surface_energy * effective_modulus * a3))
    return force, 2.0 * effective_modulus * a, a


@numba.njit(cache=True, inline="always")
def jkr_friction_load(constants, effective_radius, elastic_normal_force, normal_force):
    """Thornton & Yin (1991): an adhesive JKR contact slides when |Ft| = mu (P + 2 Fc), P
    the JKR force, Fc = 3/2 pi gamma R* (as LAMMPS' granular jkr, on the elastic force):
    positive down to the end of the curve (P >= -Fc), so the contact has friction at
    zero and at tensile load, where the total normal force would give none."""
    return elastic_normal_force + 3.0 * math.pi * constants[1] * effective_radius


def _jkr_reach(pair, constants, effective_radius):
    return jkr_critical_separation(constants["effective_modulus"], constants["surface_energy"], effective_radius)


def jkr_equilibrium_overlap(effective_modulus, surface_energy, effective_radius):
    """d at zero force: a0^3 = 9 pi gamma R*^2 / (2 E*), d0 = a0^2/R* - sqrt(2 pi gamma a0 / E*)."""
    a0 = (9.0 * math.pi * surface_energy * effective_radius**2 / (2.0 * effective_modulus)) ** (1.0 / 3.0)
    return a0 * a0 / effective_radius - math.sqrt(2.0 * math.pi * surface_energy * a0 / effective_modulus)


def _jkr_supply_bound(pair, constants, effective_radius):
    """The kinetic energy a JKR contact can give: before touch it exerts no force; from
    touch to the equilibrium overlap d0 the attraction is at most 8/9 Fc (its value at
    d = 0, falling to 0 at d0), so it does at most Fc d0 of work; beyond d0 it repels;
    in tension (d < 0) the bodies lose energy. Fc d0 bounds the well depth."""
    e, g = constants["effective_modulus"], constants["surface_energy"]
    return 1.5 * math.pi * g * effective_radius * jkr_equilibrium_overlap(e, g, effective_radius)


def _jkr_stiffness(pair, constants, effective_radius, effective_mass, normal_overlap):
    a = jkr_contact_radius.py_func(constants["effective_modulus"], constants["surface_energy"], effective_radius,
                                   normal_overlap)
    return 2.0 * constants["effective_modulus"] * a


JKR = ContactPart(
    name="jkr",
    kind="normal",
    description="JKR adhesion: formed at touch, Fn = 4E*a^3/(3R*) - sqrt(8 pi gamma E* a^3), broken at the "
                "critical separation 3/4 (pi^2 gamma^2 R*/E*^2)^(1/3); pull-off 3/2 pi gamma R*",
    parameters=(SURFACE_ENERGY,),
    constants=("effective_modulus", "surface_energy"),
    history=(HistorySlot("formed", "1 while the JKR contact is formed (touched, not yet broken)", exchange=1),),
    prepare=lambda pair, params, prepared: {"effective_modulus": pair.effective_modulus,
                                            "surface_energy": params["surface_energy"]},
    function=jkr_normal,
    energy=("store", "dissipate", "supply"),
    # Hertzian at the contact radius (Hertz's curve when gamma = 0): the Hertz dashpot
    # reads kn = 2 E* a at the JKR contact radius, as in LAMMPS' granular jkr; mindlin
    # computes its own stiffness 8 G* sqrt(R* d) from the overlap (none in tension)
    provides=("hertzian", "adhesive"),
    reach=_jkr_reach,
    contact_time=HERTZ.contact_time,  # Hertz's duration (eq 13): the time step's scale
    stiffness=_jkr_stiffness,
    supply_bound=_jkr_supply_bound,
    pull_off=lambda pair, c, radius: 1.5 * math.pi * c["surface_energy"] * radius,
    friction_load=jkr_friction_load,
    reference=JKR_REFERENCE + "; Thornton & Yin (1991), J. Phys. D 24, 1942-1946 (friction limit)",
)


@numba.njit(cache=True, inline="always")
def dmt_normal(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment, history):
    """Fn = 4/3 E* sqrt(R*) d^1.5 - 2 pi gamma R* while d > 0 (no reach: formed and broken
    at touch); the Hertz tangent stiffness and contact radius."""
    force, stiffness, contact_radius = hertz_normal(constants, effective_radius, effective_mass, normal_overlap,
                                                    normal_overlap_increment, history)
    return force - 2.0 * math.pi * constants[1] * effective_radius, stiffness, contact_radius


def _dmt_supply_bound(pair, constants, effective_radius):
    """The attraction 2 pi gamma R* acts only while the Hertz force is smaller, up to d0
    with 4/3 E* sqrt(R*) d0^1.5 = 2 pi gamma R*: the well depth is below 2 pi gamma R* d0."""
    pull = 2.0 * math.pi * constants["surface_energy"] * effective_radius
    return pull * (pull / (constants["hertz_prefactor"] * math.sqrt(effective_radius))) ** (2.0 / 3.0)


def _hertz_less_attraction(name, description, parameter, function, supply_bound, pull_off, reference):
    """A normal part on Hertz's curve less an attraction while the surfaces overlap (dmt,
    sjkr): constants 4/3 E* and the attraction's parameter, Hertz's contact time and
    stiffness (passed on to the dashpot and the time step); no reach."""
    return ContactPart(
        name=name,
        kind="normal",
        description=description,
        parameters=(parameter,),
        constants=("hertz_prefactor", parameter.name),
        history=(),
        prepare=lambda pair, params, prepared: {"hertz_prefactor": 4.0 / 3.0 * pair.effective_modulus,
                                                parameter.name: params[parameter.name]},
        function=function,
        energy=("store", "supply"),
        provides=("hertzian", "adhesive"),
        contact_time=HERTZ.contact_time,  # Hertz's duration (eq 13): the time step's scale
        stiffness=HERTZ.stiffness,
        supply_bound=supply_bound,
        pull_off=pull_off,
        reference=reference,
    )


DMT = _hertz_less_attraction(
    "dmt", "DMT adhesion: Fn = 4/3 E* sqrt(R*) d^1.5 - 2 pi gamma R* while touching; pull-off 2 pi gamma R*",
    SURFACE_ENERGY, dmt_normal, _dmt_supply_bound,
    lambda pair, c, radius: 2.0 * math.pi * c["surface_energy"] * radius, DMT_REFERENCE)

COHESION_ENERGY_DENSITY = Parameter(
    "cohesion_energy_density", None, "J/m^3", "k of the simplified JKR: cohesive force k A over the overlap "
    "area A (LIGGGHTS' cohesionEnergyDensity); per material pair through [contact.pairs]", low=0.0, required=True)
LIGGGHTS = ("LIGGGHTS-PUBLIC 3.8, gran cohesion sjkr (DCS Computing / CFDEM); Kloss et al. (2012), "
            "Prog. Comput. Fluid Dyn. 12, 140-152")


@numba.njit(cache=True, inline="always")
def sjkr_normal(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment, history):
    """Fn = 4/3 E* sqrt(R*) d^1.5 - k 2 pi R* d while d > 0 (module docstring); passes on
    Hertz's tangent stiffness and contact radius (the dashpot and Mindlin act as with
    hertz, as LIGGGHTS adds the cohesion after its normal model's damping)."""
    force, stiffness, contact_radius = hertz_normal(constants, effective_radius, effective_mass, normal_overlap,
                                                    normal_overlap_increment, history)
    return force - 2.0 * math.pi * constants[1] * effective_radius * normal_overlap, stiffness, contact_radius


def _sjkr_attraction(constants, effective_radius):
    """(K, c): Fn = K d^1.5 - c d."""
    return (constants["hertz_prefactor"] * math.sqrt(effective_radius),
            2.0 * math.pi * constants["cohesion_energy_density"] * effective_radius)


def _sjkr_supply_bound(pair, constants, effective_radius):
    """The cohesion c d does at most c d0^2 / 2 of work from touch to d0 = (c/K)^2, where
    the Hertz force takes over (the well itself is c d0^2 / 10 deep)."""
    hertz, cohesion = _sjkr_attraction(constants, effective_radius)
    return 0.5 * cohesion * (cohesion / hertz) ** 4


def _sjkr_pull_off(pair, constants, effective_radius):
    """The largest tension, at d* = (2c / 3K)^2: 4 c^3 / (27 K^2)."""
    hertz, cohesion = _sjkr_attraction(constants, effective_radius)
    return 4.0 * cohesion**3 / (27.0 * hertz**2)


SJKR = _hertz_less_attraction(
    "sjkr", "simplified JKR (LIGGGHTS cohesion sjkr): Hertz - k A while overlapping, A = 2 pi R* d the overlap "
    "area: Fn = 4/3 E* sqrt(R*) d^1.5 - 2 pi k R* d", COHESION_ENERGY_DENSITY, sjkr_normal, _sjkr_supply_bound,
    _sjkr_pull_off, LIGGGHTS)

PARTS = [JKR, DMT, SJKR]
