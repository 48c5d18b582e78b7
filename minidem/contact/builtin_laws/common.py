"""Pieces shared by the built-in laws: parameter declarations and small kernels."""

import math

import numba

from minidem.contact.laws import Parameter

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
    """
    magnitude = norm3(ftx, fty, ftz)
    if magnitude <= limit:
        return ftx, fty, ftz, False
    if magnitude == 0.0:
        return 0.0, 0.0, 0.0, True
    scale = limit / magnitude
    return ftx * scale, fty * scale, ftz * scale, True


RESTITUTION = Parameter(
    "restitution",
    1.0,
    "-",
    "normal coefficient of restitution; below 1 a viscous normal dashpot is added whose "
    "coefficient is mapped from it (exactly for the linear spring, by a calibrated "
    "dimensionless solution for Hertz)",
    low=0.0,
    high=1.0,
    low_open=True,
)


def linear_damping_ratio(restitution: float) -> float:
    """Damping ratio zeta of a linear spring-dashpot giving restitution e:
    e = exp(-zeta pi / sqrt(1 - zeta^2))  =>  zeta = -ln e / sqrt(pi^2 + ln^2 e)."""
    log_e = math.log(restitution)
    return -log_e / math.sqrt(math.pi**2 + log_e**2)


@numba.njit(cache=True)
def _hertz_dashpot_restitution(alpha):
    """Restitution of x'' = -x^1.5 - alpha x^0.25 x', x(0)=0, x'(0)=1.

    This is the dimensionless form of m d'' = -K d^1.5 - alpha sqrt(m K) d^0.25 d'
    (Tsuji et al. 1992); scaling lengths and times away leaves alpha alone, so e depends
    on alpha only, at any impact speed, mass or stiffness. Contact ends when the
    overlap returns to zero (the force is not clipped), as in the engine.
    """
    x, v = 0.0, 1.0
    h = 2.0e-4
    for _ in range(50_000_000):
        x0, v0 = x, v
        k1x, k1v = v, -max(x, 0.0) ** 1.5 - alpha * max(x, 0.0) ** 0.25 * v
        x1, v1 = x + 0.5 * h * k1x, v + 0.5 * h * k1v
        k2x, k2v = v1, -max(x1, 0.0) ** 1.5 - alpha * max(x1, 0.0) ** 0.25 * v1
        x2, v2 = x + 0.5 * h * k2x, v + 0.5 * h * k2v
        k3x, k3v = v2, -max(x2, 0.0) ** 1.5 - alpha * max(x2, 0.0) ** 0.25 * v2
        x3, v3 = x + h * k3x, v + h * k3v
        k4x, k4v = v3, -max(x3, 0.0) ** 1.5 - alpha * max(x3, 0.0) ** 0.25 * v3
        x = x + h / 6.0 * (k1x + 2 * k2x + 2 * k3x + k4x)
        v = v + h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
        if x <= 0.0 and v < 0.0:
            # linear interpolation of the exit velocity to x = 0
            frac = x0 / (x0 - x)
            return -(v0 + frac * (v - v0))
    return 0.0  # never left within the horizon: fully damped


_ALPHA_CACHE: dict[float, float] = {}


def hertz_damping_factor(restitution: float) -> float:
    """alpha such that the Hertz dashpot alpha sqrt(m* K) d^0.25 d' gives restitution e.

    Found by bisection on the dimensionless solution above (e(alpha) is monotonic);
    the restitution reproduced is e within 1e-6, checked in the tests by a full run.
    """
    if restitution >= 1.0:
        return 0.0
    if restitution in _ALPHA_CACHE:
        return _ALPHA_CACHE[restitution]
    low, high = 0.0, 1.0
    while _hertz_dashpot_restitution(high) > restitution:
        high *= 2.0
    for _ in range(60):
        mid = 0.5 * (low + high)
        if _hertz_dashpot_restitution(mid) > restitution:
            low = mid
        else:
            high = mid
    _ALPHA_CACHE[restitution] = 0.5 * (low + high)
    return _ALPHA_CACHE[restitution]


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
