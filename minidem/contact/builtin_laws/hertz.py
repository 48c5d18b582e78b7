"""Hertz normal contact with the paper's tangential models (sections 3.1, 3.3, 3.4, 5).

All five laws share the Hertz normal force Fn = 4/3 E* sqrt(R*) d^(3/2) (eq 15), with an
optional dashpot mapped from a coefficient of restitution, and differ only in the
tangential force:

    hmd                  incremental Mindlin-Deresiewicz (Thornton's form, eqs 18-24)
    hm                   incremental Mindlin no-slip, kt = 8 G* a (eq 39)
    lth                  Langston-Tuzun-Heyes, integral on the total displacement (eq 35)
    hmdns_integral       secant stiffness on the total displacement (eq 38)
    hmdns_integral_reset eq 38 with the displacement reset at the Coulomb limit (eq 40)
"""

import dataclasses
import math

import numba

from minidem.contact.builtin_laws.common import (
    FRICTION,
    RESTITUTION,
    coulomb_cap,
    damped_normal_force,
    hertz_damping_factor,
    incremental_spring,
    norm3,
)
from minidem.contact.declarations import ContactLaw, HistorySlot, Parameter

# indices into the constants row (the order of HERTZ_CONSTANTS)
(HERTZ_PREFACTOR, MINDLIN_PREFACTOR, MU, DAMPING, KAPPA, REVERSAL_CHECK, SPECIAL_CASE,
 PARTIAL_SLIP_REVERSAL_CHECK) = range(8)
HERTZ_CONSTANTS = (
    "hertz_prefactor",  # 4/3 E*, Pa: Fn = hertz_prefactor sqrt(R*) d^1.5
    "mindlin_prefactor",  # 8 G*, Pa: kt = 8 G* a, a = sqrt(R* d)
    "friction",
    "damping_factor",  # alpha: dashpot alpha sqrt(m* K) d^(1/4), K = 4/3 E* sqrt(R*)
    "stiffness_ratio",  # kappa = 4 G*/E* (eq 10)
    "reversal_check",  # hmd only, see hmd_force
    "special_case",  # hmd only: reading of eq 24, see SPECIAL_* below
    "partial_slip_reversal_check",  # hmd only: reversal in partial slip while Fn falls, see hmd_force
)


def prepare_hertz(pair, params):
    return {
        "hertz_prefactor": 4.0 / 3.0 * pair.effective_modulus,
        "mindlin_prefactor": 8.0 * pair.effective_shear_modulus,
        "friction": params["friction"],
        "damping_factor": hertz_damping_factor(params["restitution"]),
        "stiffness_ratio": pair.stiffness_ratio,
        "reversal_check": params.get("reversal_check", 1.0),
        "special_case": params.get("special_case", 0.0),
        "partial_slip_reversal_check": params.get("partial_slip_reversal_check", 1.0),
    }


def hertz_stiffness(pair, constants, effective_radius, effective_mass, normal_overlap):
    """Tangent stiffnesses at an overlap, 2 E* a and 8 G* a (a = sqrt(R* d); no law here
    is stiffer tangentially: theta <= 1 in HMD, LTH's initial slope is 8 G* a too), and
    the damping ratio of the Tsuji dashpot against the tangent normal stiffness:
    alpha sqrt(m* K) d^(1/4) / (2 sqrt(m* 3/2 K d^(1/2))) = alpha / (2 sqrt(3/2)), the
    same at every overlap."""
    a = math.sqrt(effective_radius * normal_overlap)
    return (2.0 * pair.effective_modulus * a, 8.0 * pair.effective_shear_modulus * a,
            constants["damping_factor"] / (2.0 * math.sqrt(1.5)))


@numba.njit(cache=True, inline="always")
def hertz_normal_force(constants, effective_radius, effective_mass, normal_overlap, normal_velocity):
    """Eq 15, K d^1.5 with K = 4/3 E* sqrt(R*), plus the Tsuji-type dashpot
    alpha sqrt(m* K) d^(1/4) d'.

    With the dashpot the force is clipped at zero (damped_normal_force: a non-adhesive
    contact never pulls), which is what the restitution mapping assumes. Without it
    (e = 1) the force is the elastic one, unchanged.

    Both are written with the contact radius a = sqrt(R* d), K d^1.5 = 4/3 E* a d and
    sqrt(m* K) d^(1/4) = sqrt(m* 4/3 E* a): two square roots where sqrt(R*), sqrt(d) and
    the dashpot's took three, and a is the root the tangential stiffness 8 G* a needs
    too (the compiler computes the same expression once).
    """
    contact_radius = math.sqrt(effective_radius * normal_overlap)
    elastic = constants[HERTZ_PREFACTOR] * contact_radius * normal_overlap
    if constants[DAMPING] == 0.0:
        return elastic
    return damped_normal_force(
        elastic, constants[DAMPING] * math.sqrt(effective_mass * constants[HERTZ_PREFACTOR] * contact_radius)
        * normal_velocity)


# ---------------------------------------------------------------------------------
# HMD: Thornton's incremental Mindlin-Deresiewicz law
# ---------------------------------------------------------------------------------
# History layout. The paper's law is one-dimensional; minidem applies it along a
# per-contact loading axis (a unit vector in the tangent plane, set by the first
# tangential displacement and re-aimed along the force whenever the contact slides).
# The displacement component across the axis is carried with the current tangent
# stiffness 8 G* a theta. In the paper's planar impact the cross component is zero and
# the law is exactly eqs 18-24.
FT, AXIS, FT_STAR, FT_2STAR, MODE, SLIDING = 0, 3, 6, 7, 8, 9
# the eq 19/24 special case (see SPECIAL_* and docs/laws.md): the total tangential
# displacement, whether the special state is on, and the state when it began
DISPLACEMENT, SPECIAL, ANCHOR_DISPLACEMENT, ANCHOR_FORCE, ANCHOR_NORMAL, DEFICIT = 10, 13, 14, 17, 20, 21
# the previous step's tangential increment: where the displacement reverses inside a step
PREVIOUS_INCREMENT = 22
# the previous step's normal force (with a dashpot; it depends on the velocity)
PREVIOUS_NORMAL_FORCE = 25
VIRGIN, LOADING, UNLOADING, RELOADING = 0.0, 1.0, 2.0, 3.0
# Readings of the paper's eq 24 ("theta = 1 in eq 21 UNTIL 8 G* a [.] > [.] Fn", the
# symbols lost in the extraction). theta = 1 whenever eq 19 holds (dFn > 0 and
# 8 G* a |dd| < mu dFn); the readings differ in when a special state entered there ends:
SPECIAL_STEP = 0  # at once: eq 24 is eq 19 negated, per step
SPECIAL_TOTAL = 1  # when 8 G* a |delta_t| > mu Fn, delta_t the total displacement (models.md)
SPECIAL_FORCE = 2  # when |Ft - Ft0| > mu (Fn - Fn0): accumulated eq 19, force form
SPECIAL_DISPLACEMENT = 3  # when 8 G* a |delta_t - delta_t0| > mu (Fn - Fn0): displacement form
SPECIAL_DEFICIT = 4  # when sum(mu dFn / 8 G* a) - sum(|dd| while dFn > 0) < 0
SPECIAL_COMPRESSION = 5  # when Fn stops growing (the description of Fig 11)
SPECIAL_READINGS = (SPECIAL_STEP, SPECIAL_TOTAL, SPECIAL_FORCE, SPECIAL_DISPLACEMENT, SPECIAL_DEFICIT,
                    SPECIAL_COMPRESSION)


@numba.njit(cache=True, inline="always")
def _hmd_theta(mode, force_along, ft_star, ft_2star, fn, mu):
    """theta of eqs 22a-c at one instant (the rate form: the discrete mu dFn terms of
    the paper's incremental statement vanish with dt; the step itself is integrated by
    _hmd_branch_step). Used to tell partial slip (theta < 1) at the start of a step."""
    if fn <= 0.0:
        return 1.0 if force_along == 0.0 else 0.0
    if mode == UNLOADING:
        theta_cubed = 1.0 - (ft_star - force_along) / (2.0 * mu * fn)  # 22b
    elif mode == RELOADING:
        theta_cubed = 1.0 - (force_along - ft_2star) / (2.0 * mu * fn)  # 22c
    else:
        theta_cubed = 1.0 - force_along / (mu * fn)  # 22a
    return min(max(theta_cubed, 0.0), 1.0) ** (1.0 / 3.0)


@numba.njit(cache=True, inline="always")
def _step_mean_sqrt(overlap_start, overlap_end):
    """Mean of sqrt(d) over a step in which the overlap d goes linearly from start to end,
    (2/3) (e^1.5 - s^1.5) / (e - s), written without the cancellation at e = s.

    The tangential stiffness 8 G* a, a = sqrt(R d), grows as sqrt(t) from first touch; the
    midpoint value integrates it with an error of dt^3 a'' per step, and a'' ~ t^(-3/2)
    sums to O(dt^1.5) over the contact (measured: et order 1.5 at 5 deg). The exact mean
    over the step leaves the smooth O(dt^2) part."""
    return _mean_of_roots(math.sqrt(max(overlap_start, 0.0)), math.sqrt(max(overlap_end, 0.0)))


@numba.njit(cache=True, inline="always")
def _mean_of_roots(start, end):
    """_step_mean_sqrt from the square roots at the start and the end of the step: of the
    overlaps, or of R* times them (the mean is homogeneous of degree one, so it is then
    sqrt(R*) times the mean of sqrt(d)). The Hertz laws pass the contact radii
    a = sqrt(R* d): the end's is the root their normal force takes (hertz_normal_force),
    computed once when written as the same expression (called in contact, d > 0, so
    without the max(d, 0), which would make it another one)."""
    if start + end == 0.0:
        return 0.0
    return (2.0 / 3.0) * (start * start + start * end + end * end) / (start + end)


@numba.njit(cache=True, inline="always")
def _hmd_branch_step(mode, force_along, ft_star_end, ft_2star_end, fn, dfn, mu, elastic_increment):
    """Eqs 21-23 over one step on the current branch, (Ft at the end, theta at the middle).

    Write a branch's eq 22 as theta^3 = Z / (c mu Fn): c = 1 and Z = mu Fn - Ft loading,
    c = 2 and Z = 2 mu Fn - (Ft* - Ft) unloading, 2 mu Fn - (Ft - Ft**) reloading. With
    eqs 21 and 23 in rate form, Z' = -theta h, h = 8 G* a D vt - mu Fn' (D = -1 unloading,
    +1 otherwise: the admissibility function of a reversal), so Z^(2/3) obeys

        d(Z^(2/3))/dt = -(2/3) h / (c mu Fn)^(1/3)

    whose right-hand side does not depend on the force at all: the midpoint rule on it is a
    quadrature, second order in dt up to and including the arrival at theta = 0 (the
    Coulomb limit, where Ft itself behaves as (t_c - t)^(3/2) and a midpoint step on Ft
    loses an order). Z <= 0 at the end of the step is the Coulomb limit reached inside it,
    and the force is then exactly on it, wherever in the step that happened."""
    fn_start = fn - dfn
    fn_mid = fn - 0.5 * dfn
    if fn_start <= 0.0 or fn_mid <= 0.0 or fn <= 0.0:
        # no contact area at the start: eq 21 with theta = 1 (the cap of the caller acts)
        return force_along + elastic_increment, 1.0
    if mode == UNLOADING:
        reach = 2.0
        distance = (ft_star_end - mu * dfn) - force_along
        direction = -1.0
    elif mode == RELOADING:
        reach = 2.0
        distance = force_along - (ft_2star_end + mu * dfn)
        direction = 1.0
    else:
        reach = 1.0
        distance = force_along
        direction = 1.0
    if distance <= 0.0:
        # the force is at or ahead of the branch's reversal point: eq 22 clipped gives
        # theta = 1, eq 21 is elastic, as long as it stays there (a branch that began
        # where the Coulomb limit shrinks faster than the elastic force, which the
        # admissibility test of partial_slip_reversal_check = 1 prevents)
        elastic_end = force_along + elastic_increment
        if mode == UNLOADING:
            distance_elastic = ft_star_end - elastic_end
        elif mode == RELOADING:
            distance_elastic = elastic_end - ft_2star_end
        else:
            distance_elastic = elastic_end
        if distance_elastic <= 0.0:
            return elastic_end, 1.0
    reach_start = reach * mu * fn_start
    z_start = min(max(reach_start - distance, 0.0), reach_start)
    s_start = z_start ** (2.0 / 3.0)
    # h over the step: 8 G* a(mid) D dd - mu dFn
    admissibility = direction * elastic_increment - mu * dfn
    scale_mid = (reach * mu * fn_mid) ** (1.0 / 3.0)
    s_end = s_start - (2.0 / 3.0) * admissibility / scale_mid
    reach_end = reach * mu * fn
    z_end = max(s_end, 0.0) ** 1.5
    if z_end > reach_end:
        # theta reaches 1 within the step (the force overtakes the reversal point, Ft*
        # falling faster under eq 23 than Ft does): eq 22 clipped, eq 21 elastic. Its rate
        # equals the branch's at theta = 1, so the whole step is taken elastic.
        return force_along + elastic_increment, 1.0
    distance_end = reach_end - z_end
    s_mid = max(0.5 * (s_start + s_end), 0.0)
    theta = min(math.sqrt(s_mid) / scale_mid, 1.0)
    if mode == UNLOADING:
        return ft_star_end - distance_end, theta
    if mode == RELOADING:
        return ft_2star_end + distance_end, theta
    return distance_end, theta


@numba.njit(cache=True, inline="always")
def _meets_mirrored_curve(force_start, star_start, force_end, star_end):
    """True when, with Ft and Ft* linear over the step, the unloading branch reaches the
    mirrored virgin curve at some instant: Ft <= -Ft* while Ft* > 0 (a full reversal).

    Testing the end of the step alone misses it when eq 23 takes Ft* through the window
    (0, -Ft] within one step (mu dFn per step larger than |Ft|: at 1 deg from mu ~ 1.2
    at 4000 steps per contact), and the decision then depends on the step. The set is
    where max(Ft + Ft*, -Ft*) <= 0; that function is convex along the step, so it is
    inside the set somewhere iff it is at the end or at the kink Ft + 2 Ft* = 0, where
    the test is Ft* > 0."""
    if star_end > 0.0 and force_end + star_end <= 0.0:
        return True
    kink_start = force_start + 2.0 * star_start
    kink_end = force_end + 2.0 * star_end
    if (kink_start > 0.0) == (kink_end > 0.0):
        return False
    fraction = kink_start / (kink_start - kink_end)
    return star_start + fraction * (star_end - star_start) > 0.0


@numba.njit(cache=True, inline="always")
def _special_margin(reading, history, ftx, fty, ftz, fn, stiffness, mu):
    """> 0 while the special state entered under eq 19 goes on (readings 1-3)."""
    sx, sy, sz = history[DISPLACEMENT], history[DISPLACEMENT + 1], history[DISPLACEMENT + 2]
    if reading == SPECIAL_TOTAL:
        return mu * fn - stiffness * norm3(sx, sy, sz)
    normal_gain = mu * (fn - history[ANCHOR_NORMAL])
    if reading == SPECIAL_FORCE:
        return normal_gain - norm3(ftx - history[ANCHOR_FORCE], fty - history[ANCHOR_FORCE + 1],
                                   ftz - history[ANCHOR_FORCE + 2])
    return normal_gain - stiffness * norm3(sx - history[ANCHOR_DISPLACEMENT], sy - history[ANCHOR_DISPLACEMENT + 1],
                                           sz - history[ANCHOR_DISPLACEMENT + 2])


@numba.njit(cache=True)
def hmd_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
              normal_velocity, tangential_increment, tangential_velocity, history):
    normal_force = hertz_normal_force(constants, effective_radius, effective_mass, normal_overlap, normal_velocity)
    mu = constants[MU]
    if mu == 0.0:
        return normal_force, 0.0, 0.0, 0.0
    # Mindlin-Deresiewicz's N, in theta (eq 22), dFn (eqs 19, 21, 23) and the Coulomb cap,
    # is one force: the normal force the contact transmits, which Coulomb's law refers
    # to. With a dashpot that is the total, clipped force: with the elastic one in theta
    # and the total one in the cap, a sliding contact at e = 0.5 carried 0.82 of mu times
    # the normal impulse (issue 16). Its previous value is kept, as the dashpot's part
    # depends on the velocity. Without a dashpot (e = 1) the two are the elastic force,
    # computed as before.
    if constants[DAMPING] == 0.0:
        stiffness = constants[HERTZ_PREFACTOR] * math.sqrt(effective_radius)
        fn = stiffness * normal_overlap ** 1.5
        fn_old = stiffness * max(normal_overlap - normal_overlap_increment, 0.0) ** 1.5
    else:
        fn = normal_force
        fn_old = history[PREVIOUS_NORMAL_FORCE]
        history[PREVIOUS_NORMAL_FORCE] = fn
    dfn = fn - fn_old
    # 8 G* a averaged over the step (the overlap linear in it): with the end-of-step
    # radius the update is only first order in dt, and with the mid-step radius the
    # sqrt(t) growth of a after first touch costs half an order (see _step_mean_sqrt)
    # (a = sqrt(R* d) at both ends: _step_mean_sqrt times sqrt(R*), the end's root shared
    # with hertz_normal_force)
    stick_stiffness = constants[MINDLIN_PREFACTOR] * _mean_of_roots(
        math.sqrt(effective_radius * max(normal_overlap - normal_overlap_increment, 0.0)),
        math.sqrt(effective_radius * normal_overlap))
    limit = mu * max(normal_force, 0.0)
    reading = int(constants[SPECIAL_CASE])

    ddx, ddy, ddz = tangential_increment[0], tangential_increment[1], tangential_increment[2]
    ax, ay, az = history[AXIS], history[AXIS + 1], history[AXIS + 2]
    if ax == 0.0 and ay == 0.0 and az == 0.0:
        increment = norm3(ddx, ddy, ddz)
        if increment == 0.0:
            return normal_force, 0.0, 0.0, 0.0
        ax, ay, az = ddx / increment, ddy / increment, ddz / increment
        history[MODE] = LOADING
    along = ddx * ax + ddy * ay + ddz * az
    ftx, fty, ftz = history[FT], history[FT + 1], history[FT + 2]
    force_along = ftx * ax + fty * ay + ftz * az  # Ft in the paper's 1-D sense
    cross_x, cross_y, cross_z = ftx - force_along * ax, fty - force_along * ay, ftz - force_along * az

    # eq 19: a tangential increment too small for the normal one causes no slip
    eq19 = dfn > 0.0 and stick_stiffness * abs(along) < mu * dfn
    special = False
    if reading == SPECIAL_STEP:
        special = eq19
    elif reading == SPECIAL_DEFICIT:
        # the displacement still owed before the force is back on the loading curve of
        # the current Fn: grows by mu dFn / 8 G* a - |dd| while Fn grows, shrinks by
        # mu |dFn| / 8 G* a while it falls (geoLAMMPS' HMD pair style)
        deficit = history[DEFICIT] + (mu * dfn / stick_stiffness if stick_stiffness > 0.0 else 0.0)
        if dfn > 0.0:
            deficit -= abs(along)
        special = deficit > 0.0
        history[DEFICIT] = max(deficit, 0.0)
    else:
        special = history[SPECIAL] != 0.0 or eq19
        if reading == SPECIAL_COMPRESSION and dfn <= 0.0:
            special = False
        if eq19 and history[SPECIAL] == 0.0:
            # the state at the start of the step, where the special state begins
            history[ANCHOR_DISPLACEMENT] = history[DISPLACEMENT]
            history[ANCHOR_DISPLACEMENT + 1] = history[DISPLACEMENT + 1]
            history[ANCHOR_DISPLACEMENT + 2] = history[DISPLACEMENT + 2]
            history[ANCHOR_FORCE], history[ANCHOR_FORCE + 1], history[ANCHOR_FORCE + 2] = ftx, fty, ftz
            history[ANCHOR_NORMAL] = fn_old
    history[DISPLACEMENT] += ddx
    history[DISPLACEMENT + 1] += ddy
    history[DISPLACEMENT + 2] += ddz

    mode = history[MODE]
    # load-reversal points at the start of the step; eq 23 moves them by mu dFn over it
    ft_star = history[FT_STAR]
    ft_2star = history[FT_2STAR]

    # A reversal point is where the displacement rate changed sign, between the middle
    # of the previous step (increment `previous_along`) and the middle of this one
    # (`along`): at a fraction reversal_lag = previous/(previous - along) of a step after
    # the previous middle, i.e. (reversal_lag - 1/2) of a step into this one. Eq 23 then
    # moves the new Ft* or Ft** by mu dFn over the rest of the step only: without this
    # the reversal point was off by up to mu dFn / 2 depending on where in its step the
    # reversal fell, an O(mu dt) error in et that jumped with the step count (3.7e-3 at
    # mu = 5, 0.5 deg between 3990 and 4010 steps per contact).
    previous_along = history[PREVIOUS_INCREMENT] * ax + history[PREVIOUS_INCREMENT + 1] * ay \
        + history[PREVIOUS_INCREMENT + 2] * az
    history[PREVIOUS_INCREMENT], history[PREVIOUS_INCREMENT + 1], history[PREVIOUS_INCREMENT + 2] = ddx, ddy, ddz
    reversal_shift = 0.0  # mu dFn times the part of the step before the reversal
    if previous_along * along < 0.0:
        reversal_lag = previous_along / (previous_along - along)
        reversal_shift = mu * dfn * (reversal_lag - 0.5)

    # A reversed increment in partial slip while Fn falls (issue 13, models.md "The
    # reading that gives the paper's 4 %"): the new branch would start elastic (theta = 1)
    # and unload at 8 G* a |dd|, slower than the Coulomb limit mu Fn shrinks (mu |dFn|),
    # so its eq-22 theta would exceed 1. The current branch goes on under eq 21 with the
    # actual increment until 8 G* a |dd| > mu |dFn|, and reverses there. At that crossing
    # the old branch moves Ft by mu dFn a step (eq 21 with 8 G* a dd = mu dFn) and so does
    # eq 23 move Ft*: the new reversal point is Ft at the start of the step plus the whole
    # step's mu dFn, wherever in the step the crossing lay (reversal_shift = 0). Full slip
    # (theta = 0) is the same test, made by reversal_check below.
    direction = -1.0 if mode == UNLOADING else 1.0
    holds_branch = False
    if (constants[PARTIAL_SLIP_REVERSAL_CHECK] != 0.0 and dfn < 0.0 and not special and history[SLIDING] == 0.0
            and direction * along < 0.0
            and _hmd_theta(mode, force_along, ft_star, ft_2star, fn - dfn, mu) < 1.0):
        reversal_shift = 0.0
        holds_branch = stick_stiffness * abs(along) <= -mu * dfn
    stays_sliding = False
    if holds_branch:
        pass  # not admissible yet: no branch switch below
    elif history[SLIDING] != 0.0 and constants[REVERSAL_CHECK] != 0.0:
        # While sliding, a reversed displacement starts unloading only when the elastic
        # trial force is back inside the Coulomb cone (the test LS and HM make); with
        # reversal_check = 0 the branch reverses the instant the displacement does.
        if force_along + stick_stiffness * along >= limit:
            stays_sliding = True
        elif along < 0.0:
            mode = UNLOADING
            ft_star = force_along - reversal_shift
    elif mode == LOADING and along < 0.0:
        mode = UNLOADING
        ft_star = force_along - reversal_shift
    elif mode == UNLOADING and along > 0.0:
        mode = RELOADING
        ft_2star = force_along + reversal_shift
    elif mode == RELOADING and along < 0.0:
        mode = UNLOADING
        ft_star = force_along - reversal_shift

    if stays_sliding:
        force_along = limit
        cross_x, cross_y, cross_z = 0.0, 0.0, 0.0
    else:
        force_start, star_start = force_along, ft_star
        ft_star += mu * dfn  # eq 23
        ft_2star -= mu * dfn
        if special:
            theta = 1.0  # eqs 19 and 24: increments below mu dFn cause no slip
            force_along += stick_stiffness * along  # eq 21 with theta = 1
        else:
            force_along, theta = _hmd_branch_step(mode, force_along, ft_star, ft_2star, fn, dfn, mu,
                                                  stick_stiffness * along)
        tangent_stiffness = stick_stiffness * theta
        cross_x += tangent_stiffness * (ddx - along * ax)
        cross_y += tangent_stiffness * (ddy - along * ay)
        cross_z += tangent_stiffness * (ddz - along * az)
        if mode == RELOADING and force_along >= ft_star:
            mode = LOADING  # back on the virgin curve: the reversal memory is erased
        elif mode == UNLOADING and _meets_mirrored_curve(force_start, star_start, force_along, ft_star):
            # full reversal (Masing): the unloading branch has met the mirrored virgin
            # curve at -Ft*, so the contact forgets Ft* and loads afresh the other way.
            # Eq 23 drives Ft* below zero once Fn has fallen by more than
            # (mu Fn_rev - Ft_rev)/mu; -Ft* is then no reversal point at all, and the
            # unloading branch (theta = 1 there) continues until the Coulomb cap. The
            # test is made along the step, not at its end (see _meets_mirrored_curve).
            ax, ay, az = -ax, -ay, -az
            force_along = -force_along
            cross_x, cross_y, cross_z = -cross_x, -cross_y, -cross_z
            mode = LOADING

    ftx = force_along * ax + cross_x
    fty = force_along * ay + cross_y
    ftz = force_along * az + cross_z
    ftx, fty, ftz, capped = coulomb_cap(ftx, fty, ftz, limit)
    sliding = capped or stays_sliding
    if sliding:
        magnitude = norm3(ftx, fty, ftz)
        if magnitude > 0.0:
            ax, ay, az = ftx / magnitude, fty / magnitude, ftz / magnitude
        mode = LOADING
        ft_star = magnitude
        ft_2star = -magnitude
        special = False  # on the Coulomb limit the force is on every curve
        history[DEFICIT] = 0.0
    elif special and not eq19 and reading in (SPECIAL_TOTAL, SPECIAL_FORCE, SPECIAL_DISPLACEMENT):
        # the end condition is tested only once eq 19 has stopped holding (as the
        # reference solver's event does), so the anchor stays where the state began
        end_stiffness = constants[MINDLIN_PREFACTOR] * math.sqrt(effective_radius * normal_overlap)
        special = _special_margin(reading, history, ftx, fty, ftz, fn, end_stiffness, mu) > 0.0
    history[SPECIAL] = 1.0 if special else 0.0
    history[FT], history[FT + 1], history[FT + 2] = ftx, fty, ftz
    history[AXIS], history[AXIS + 1], history[AXIS + 2] = ax, ay, az
    history[FT_STAR], history[FT_2STAR] = ft_star, ft_2star
    history[MODE] = mode
    history[SLIDING] = 1.0 if sliding else 0.0
    return normal_force, ftx, fty, ftz


# ---------------------------------------------------------------------------------
# HM: incremental Mindlin no-slip (eq 39)
# ---------------------------------------------------------------------------------
@numba.njit(cache=True)
def hm_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
             normal_velocity, tangential_increment, tangential_velocity, history):
    normal_force = hertz_normal_force(constants, effective_radius, effective_mass, normal_overlap, normal_velocity)
    # eq 39 integrated with the stiffness averaged over the step (as hmd's): the
    # end-of-step contact radius makes the update first order in dt, the mid-step one
    # order 1.5 (measured against the reference; see _step_mean_sqrt). The mean is that of
    # the contact radius a = sqrt(R* d), whose value at the end of the step
    # hertz_normal_force has computed (normal_overlap > 0: the law acts in contact only)
    stiffness = constants[MINDLIN_PREFACTOR] * _mean_of_roots(
        math.sqrt(effective_radius * max(normal_overlap - normal_overlap_increment, 0.0)),
        math.sqrt(effective_radius * normal_overlap))
    ftx, fty, ftz = incremental_spring(history, stiffness, tangential_increment,
                                       constants[MU] * max(normal_force, 0.0))
    return normal_force, ftx, fty, ftz


# ---------------------------------------------------------------------------------
# Integral laws on the total tangential displacement (eqs 35, 38, 40)
# ---------------------------------------------------------------------------------
@numba.njit(cache=True, inline="always")
def _accumulate_displacement(history, tangential_increment):
    history[0] += tangential_increment[0]
    history[1] += tangential_increment[1]
    history[2] += tangential_increment[2]
    return history[0], history[1], history[2]


@numba.njit(cache=True, inline="always")
def _secant_force(constants, effective_radius, effective_mass, normal_overlap, normal_velocity,
                  tangential_increment, history, reset):
    normal_force = hertz_normal_force(constants, effective_radius, effective_mass, normal_overlap, normal_velocity)
    stiffness = constants[MINDLIN_PREFACTOR] * math.sqrt(effective_radius * normal_overlap)
    sx, sy, sz = _accumulate_displacement(history, tangential_increment)
    ftx, fty, ftz, sliding = coulomb_cap(stiffness * sx, stiffness * sy, stiffness * sz,
                                         constants[MU] * max(normal_force, 0.0))
    if reset and sliding:
        # eq 40: the stored displacement becomes the elastic one, mu Fn / kt
        history[0], history[1], history[2] = ftx / stiffness, fty / stiffness, ftz / stiffness
    return normal_force, ftx, fty, ftz


@numba.njit(cache=True)
def integral_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                   normal_velocity, tangential_increment, tangential_velocity, history):
    return _secant_force(constants, effective_radius, effective_mass, normal_overlap, normal_velocity,
                         tangential_increment, history, False)


@numba.njit(cache=True)
def integral_reset_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                         normal_velocity, tangential_increment, tangential_velocity, history):
    return _secant_force(constants, effective_radius, effective_mass, normal_overlap, normal_velocity,
                         tangential_increment, history, True)


@numba.njit(cache=True)
def lth_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
              normal_velocity, tangential_increment, tangential_velocity, history):
    normal_force = hertz_normal_force(constants, effective_radius, effective_mass, normal_overlap, normal_velocity)
    sx, sy, sz = _accumulate_displacement(history, tangential_increment)
    displacement = norm3(sx, sy, sz)
    if displacement == 0.0:
        return normal_force, 0.0, 0.0, 0.0
    mu = constants[MU]
    # eq 32: sliding displacement d* = mu d / kappa
    sliding_displacement = mu * normal_overlap / constants[KAPPA]
    if sliding_displacement <= 0.0:
        return normal_force, 0.0, 0.0, 0.0
    ratio = min(displacement / sliding_displacement, 1.0)
    # eq 35. The min() is the whole of Langston et al.'s "if |s| > s* then |s| = s*": the
    # stored total displacement is not cut back to s*, no elastic displacement is
    # computed (the paper's appendix: that is what makes LTH slide throughout from
    # about 20 deg and create energy, Figs 8-10)
    magnitude = mu * max(normal_force, 0.0) * (1.0 - (1.0 - ratio) ** 1.5)
    return normal_force, magnitude * sx / displacement, magnitude * sy / displacement, magnitude * sz / displacement


@dataclasses.dataclass(frozen=True)
class _Choice(Parameter):
    """A parameter that selects one of the integers low..high."""

    def check(self, value):
        why = super().check(value)
        if why is None and float(value) != int(value):
            return f"must be one of the integers {self.low:g}..{self.high:g}, got {value!r}"
        return why

    def bounds_text(self) -> str:
        return f"one of the integers {self.low:g}..{self.high:g}"


def _law(name, description, force, history, reference, aliases=(), extra=()):
    return ContactLaw(
        name=name,
        description=description,
        parameters=(FRICTION, RESTITUTION) + extra,
        constants=HERTZ_CONSTANTS,
        history=history,
        prepare=prepare_hertz,
        force=force,
        aliases=aliases,
        reference=reference,
        stiffness=hertz_stiffness,
        normal_part="hertz",  # its first constant is the hertz part's 4/3 E*
    )


_FORCE_SLOT = (HistorySlot("tangential_force", "spring force in the tangent plane (N)", vector=True, exchange=-1),)
_DISPLACEMENT_SLOT = (HistorySlot("tangential_displacement", "total tangential displacement (m)", vector=True,
                                  exchange=-1),)

HMD = _law(
    "hmd",
    "Hertz + Mindlin-Deresiewicz, Thornton's incremental form with load-reversal memory (eqs 15-24)",
    hmd_force,
    _FORCE_SLOT + (
        HistorySlot("loading_axis", "unit loading direction in the tangent plane", vector=True, exchange=-1),
        HistorySlot("ft_star", "load-reversal point Ft* along the axis (N)", exchange=1),
        HistorySlot("ft_2star", "load-reversal point Ft** along the axis (N)", exchange=1),
        HistorySlot("mode", "0 virgin, 1 loading, 2 unloading, 3 reloading", exchange=1),
        HistorySlot("sliding", "1 while the force is on the Coulomb limit", exchange=1),
        HistorySlot("tangential_displacement", "total tangential displacement (m)", vector=True, exchange=-1),
        HistorySlot("special", "1 while theta = 1 under eqs 19/24 (special_case 1-3)", exchange=1),
        HistorySlot("special_start_displacement", "total displacement where the special state began (m)",
                    vector=True, exchange=-1),
        HistorySlot("special_start_force", "tangential force where the special state began (N)", vector=True,
                    exchange=-1),
        HistorySlot("special_start_normal_force", "normal force where the special state began (N)", exchange=1),
        HistorySlot("special_deficit", "displacement owed before the loading curve is met (m; special_case 4)",
                    exchange=1),
        HistorySlot("previous_increment", "the previous step's tangential displacement increment (m)",
                    vector=True, exchange=-1),
        HistorySlot("previous_normal_force", "the previous step's normal force, with a dashpot (N)", exchange=1),
    ),
    "Thornton, Cummins & Cleary (2011) section 3.1; Thornton & Yin (1991)",
    aliases=("hertz_mindlin_deresiewicz",),
    extra=(_Choice("reversal_check", 1.0, "-", "1: while sliding, reverse to unloading only when "
                     "the elastic trial force is inside the Coulomb cone; 0: reverse the instant "
                     "the displacement does (see docs/laws.md)", low=0.0, high=1.0),
           _Choice("special_case", 0.0, "-", "reading of eq 24, when the theta = 1 state entered "
                   "under eq 19 ends: 0 per step (eq 19 negated), 1 8 G* a |delta_t| > mu Fn, "
                   "2 |Ft - Ft0| > mu (Fn - Fn0), 3 8 G* a |delta_t - delta_t0| > mu (Fn - Fn0), "
                   "4 accumulated displacement deficit, 5 when Fn stops growing (see docs/laws.md)", low=0.0,
                   high=5.0),
           _Choice("partial_slip_reversal_check", 1.0, "-", "1: while Fn decreases in partial slip "
                   "(theta < 1), a reversed increment starts the new branch only once it is admissible, "
                   "8 G* a |d(delta_t)| > mu |dFn|, the current branch going on under eq 21 until then "
                   "(the reading that gives the paper's 4 % at 1 deg); 0: at once, when the increment "
                   "reverses (minidem before issue 13; see docs/laws.md)", low=0.0, high=1.0)),
)
HM = _law("hm", "Hertz + Mindlin no-slip, incremental Ft += 8 G* a dd (eq 39)", hm_force, _FORCE_SLOT,
          "Thornton, Cummins & Cleary (2011) section 3.3", aliases=("hertz_mindlin",))
LTH = _law("lth", "Langston-Tuzun-Heyes: Ft = mu Fn [1 - (1 - min(|s|/s*, 1))^1.5] on the total "
           "displacement (eq 35)", lth_force, _DISPLACEMENT_SLOT,
           "Thornton, Cummins & Cleary (2011) section 3.4")
INTEGRAL = _law("hmdns_integral", "Hertz + Mindlin, secant Ft = 8 G* a s on the total displacement "
                "(eq 38, Di Renzo & Di Maio's H-MDns); creates energy", integral_force, _DISPLACEMENT_SLOT,
                "Thornton, Cummins & Cleary (2011) section 5", aliases=("h-mdns", "integral"))
INTEGRAL_RESET = _law("hmdns_integral_reset", "eq 38 with the displacement reset to mu Fn / kt at "
                      "the Coulomb limit (eq 40; LIGGGHTS' default Hertz)", integral_reset_force,
                      _DISPLACEMENT_SLOT, "Thornton, Cummins & Cleary (2011) section 5 and appendix",
                      aliases=("integral_reset",))

LAWS = [HMD, HM, LTH, INTEGRAL, INTEGRAL_RESET]
