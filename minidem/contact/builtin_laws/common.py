"""Pieces shared by the built-in laws: parameter declarations and small kernels."""

import math

import numba

from minidem.contact.declarations import Parameter

FRICTION = Parameter(
    "friction", None, "-", "Coulomb friction coefficient mu", low=0.0, required=True
)


@numba.njit(cache=True, inline="always")
def norm3(vx, vy, vz):
    return math.sqrt(vx * vx + vy * vy + vz * vz)


@numba.njit(cache=True, inline="always")
def coulomb_cap(ftx, fty, ftz, limit):
    """Scale a tangential force back onto the Coulomb cone |Ft| <= limit.

    Returns the capped force and whether the cap was active (sliding).

    The test compares squares (limit >= 0 here: mu max(Fn, 0) or a rolling limit), so
    the square root is taken only for a contact that slides: in a settling pile (settle
    scene, hm, N = 20,000) four contacts in five stick, and the root was one of eight
    on each contact's dependency chain.
    """
    squared = ftx * ftx + fty * fty + ftz * ftz
    if squared <= limit * limit:
        return ftx, fty, ftz, False
    magnitude = math.sqrt(squared)
    if magnitude == 0.0:
        return 0.0, 0.0, 0.0, True
    scale = limit / magnitude
    return ftx * scale, fty * scale, ftz * scale, True


RESTITUTION = Parameter(
    "restitution",
    1.0,
    "-",
    "normal coefficient of restitution; below 1 a viscous normal dashpot is added whose "
    "coefficient is mapped from it (in closed form for the linear spring, by a calibrated "
    "dimensionless solution for Hertz), the normal force clipped at zero (never tensile)",
    low=0.0,
    high=1.0,
    low_open=True,
)


@numba.njit(cache=True, inline="always")
def damped_normal_force(elastic, dashpot):
    """The normal force of a non-adhesive contact with a dashpot: elastic + dashpot,
    clipped at zero.

    A contact that cannot stick cannot pull: while the dashpot would pull harder than the
    spring pushes (the overlap closing fast), the force is zero and the bodies move apart
    freely (LAMMPS' granular ``limit_damping``). The Coulomb limit mu Fn then acts on the
    same force whose impulse is the normal impulse, so a sliding contact's tangential
    impulse is mu times the normal impulse, as Coulomb's law of impact states. The
    restitution mappings below (linear_damping_ratio, hertz_damping_factor) are those of
    this clipped force. Adhesive normal parts (which provide 'adhesive') keep their
    tension and are not clipped (minidem.contact.compose).
    """
    return max(elastic + dashpot, 0.0)


@numba.njit(cache=True)
def linear_dashpot_restitution(damping_ratio):
    """Restitution of the clipped linear spring-dashpot m x'' = -kn x - c x', force
    max(kn x + c x', 0), c = 2 zeta sqrt(m kn) (Schwager & Poeschel 2007, Phys. Rev. E
    75, 051304; derived again here).

    With omega0 = 1: x = e^(-zeta t) sin(w t)/w, w = sqrt(1 - zeta^2). The force
    x + 2 zeta x' vanishes in restitution at w t = pi - atan2(2 zeta w, 1 - 2 zeta^2),
    where sin(w t) = 2 zeta w, so there x' = -x / (2 zeta) = -e^(-zeta t): the body leaves
    with e = exp(-zeta t_c), before the overlap has closed. Overdamped (zeta > 1,
    W = sqrt(zeta^2 - 1)): t_c = ln((zeta + W)/(zeta - W)) / W, again e = exp(-zeta t_c);
    at zeta = 1 both give t_c = 2. e falls from 1 (zeta = 0) to 0 (zeta -> infinity, as
    1/(4 zeta^2)) monotonically.
    """
    if damping_ratio <= 0.0:
        return 1.0
    if damping_ratio < 1.0:
        w = math.sqrt(1.0 - damping_ratio * damping_ratio)
        duration = (math.pi - math.atan2(2.0 * damping_ratio * w, 1.0 - 2.0 * damping_ratio * damping_ratio)) / w
    elif damping_ratio == 1.0:
        duration = 2.0
    else:
        # ln((zeta + W)/(zeta - W)) = 2 ln(zeta + W), their product being 1: the quotient
        # divided by zero once zeta - W rounded to 0 (e below ~1e-17, restitution = 1e-20:
        # a robustness review), and zeta^2 overflows before W does as zeta sqrt(1 - 1/zeta^2)
        w = damping_ratio * math.sqrt(1.0 - 1.0 / (damping_ratio * damping_ratio))
        duration = 2.0 * math.log(damping_ratio + w) / w
    return math.exp(-damping_ratio * duration)


def _damping_for(restitution: float, restitution_of, cache: dict) -> float:
    """The damping (>= 0) whose restitution_of(damping) is e: bisection, restitution_of
    falling monotonically from 1 at zero damping to 0 at infinite damping. The upper
    bound doubles from 1 until it gives less than e; 60 halvings then leave the damping
    to round-off. Memoised in ``cache`` (per mapping)."""
    if restitution >= 1.0:
        return 0.0
    if restitution not in cache:
        low, high = 0.0, 1.0
        while restitution_of(high) > restitution:
            low, high = high, 2.0 * high
        for _ in range(60):
            mid = 0.5 * (low + high)
            if restitution_of(mid) > restitution:
                low = mid
            else:
                high = mid
        cache[restitution] = 0.5 * (low + high)
    return cache[restitution]


_ZETA_CACHE: dict[float, float] = {}


def linear_damping_ratio(restitution: float) -> float:
    """Damping ratio zeta of the clipped linear spring-dashpot that gives restitution e:
    linear_dashpot_restitution inverted by bisection. No longer -ln e / sqrt(pi^2 + ln^2 e),
    which is the unclipped dashpot's (the contact ending at zero overlap, the force tensile
    at the end): clipped at zero, the same zeta gives a larger e."""
    return _damping_for(restitution, linear_dashpot_restitution, _ZETA_CACHE)


@numba.njit(cache=True, inline="always")
def _tsuji_force(x, v, alpha):
    """x^1.5 + alpha x^0.25 v (x clipped at 0), x^0.25 from two square roots: a float
    power is a call of the C library's pow, and five of them a step made this solution
    0.1 s of every run's set-up (61 bisection steps)."""
    quarter = math.sqrt(math.sqrt(max(x, 0.0)))
    return max(x, 0.0) * quarter * quarter + alpha * quarter * v


@numba.njit(cache=True)
def _hertz_dashpot_restitution(alpha):
    """Restitution of x'' = -f, f = max(x^1.5 + alpha x^0.25 x', 0), x(0)=0, x'(0)=1.

    This is the dimensionless form of m d'' = -max(K d^1.5 + alpha sqrt(m K) d^0.25 d', 0)
    (Tsuji et al. 1992, clipped as damped_normal_force clips it); scaling lengths and
    times away leaves alpha alone, so e depends on alpha only, at any impact speed, mass
    or stiffness. The body leaves when the force reaches zero in restitution (x' < 0),
    with its speed then (the overlap closes afterwards without force): RK4, the exit
    speed interpolated linearly in f to f = 0.
    """
    x, v = 0.0, 1.0
    h = 2.0e-4
    force_old = 0.0
    for _ in range(50_000_000):
        v0 = v
        k1x, k1v = v, -max(_tsuji_force(x, v, alpha), 0.0)
        x1, v1 = x + 0.5 * h * k1x, v + 0.5 * h * k1v
        k2x, k2v = v1, -max(_tsuji_force(x1, v1, alpha), 0.0)
        x2, v2 = x + 0.5 * h * k2x, v + 0.5 * h * k2v
        k3x, k3v = v2, -max(_tsuji_force(x2, v2, alpha), 0.0)
        x3, v3 = x + h * k3x, v + h * k3v
        k4x, k4v = v3, -max(_tsuji_force(x3, v3, alpha), 0.0)
        x = x + h / 6.0 * (k1x + 2 * k2x + 2 * k3x + k4x)
        v = v + h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
        force = _tsuji_force(x, v, alpha)
        if v < 0.0 and (force <= 0.0 or x <= 0.0):
            frac = force_old / (force_old - force) if force_old != force else 1.0
            return -(v0 + frac * (v - v0))
        force_old = force
    return 0.0  # never left within the horizon: fully damped


_ALPHA_CACHE: dict[float, float] = {}


def hertz_damping_factor(restitution: float) -> float:
    """alpha such that the clipped Hertz dashpot alpha sqrt(m* K) d^0.25 d' gives
    restitution e: the dimensionless solution above inverted by bisection; the
    restitution reproduced is e within 1e-6, checked in the tests by an independent
    integration and by full runs."""
    return _damping_for(restitution, _hertz_dashpot_restitution, _ALPHA_CACHE)


@numba.njit(cache=True, inline="always")
def incremental_spring(history, stiffness, tangential_increment, limit):
    """Ft_new = Ft_old + kt dd, capped at the Coulomb limit (eqs 26 and 39).

    The force is kept in history slots 0-2 (a vector slot, so the engine keeps it in
    the current tangent plane).
    """
    ftx = history[0] + stiffness * tangential_increment[0]
    fty = history[1] + stiffness * tangential_increment[1]
    ftz = history[2] + stiffness * tangential_increment[2]
    ftx, fty, ftz, _ = coulomb_cap(ftx, fty, ftz, limit)
    history[0], history[1], history[2] = ftx, fty, ftz
    return ftx, fty, ftz
