"""Independent high-accuracy solution of the single sphere-wall impact (reference only).

Used to measure the error of the explicit engine (``minidem bench``, tests); it shares no
code with the engine or the laws in ``minidem/contact/builtin_laws``: the laws are re-derived here
from Thornton, Cummins & Cleary (2011) and ``../shared/paper/models.md`` in RATE form.

The problem is the paper's 2-D one: normal overlap ``delta`` with approach speed ``u``,
the centre's tangential velocity ``vt`` and the surface speed of spin ``wr = R omega``
(the contact point slides at ``vs = vt + wr``). With the tangential force ``Ft`` in the
sense of the tangential displacement (the wall pushes the sphere with -Ft)::

    delta' = u,  m u' = -Fn,  m vt' = -Ft,  m wr' = -(m R^2 / I) Ft = -5/2 Ft

and per law (``q`` is Ft for the incremental laws, the total displacement s for the
integral ones; ``f1``, ``f2`` are HMD's load-reversal points Ft*, Ft**):

    ls      stick  Ft' = kt vs                       slide  Ft = mu Fn sign
    hm      stick  Ft' = 8 G* a vs                   slide  Ft = mu Fn sign
    hmd     Ft' = 8 G* a theta vs +/- mu Fn' (1 - theta)   (eq 21, theta from eq 22 with the
            increments -> 0; theta = 1 while Fn' > 0 and 8 G* a |vs| < mu Fn', eqs 19/24,
            and in the special state of the chosen reading of eq 24);
            f1' = mu Fn', f2' = -mu Fn' (eq 23); S' = vs (total displacement), D' the
            deficit rate of special_case 4
    lth     s' = vs, Ft = mu Fn [1 - (1 - min(|s|/s*, 1))^1.5] sign(s), s* = mu delta / kappa,
            on the total displacement (eq 35; no cut-back of s at s*, as the engine's law:
            see docs/laws.md)
    hmdns_integral        s' = vs, Ft = 8 G* a s capped at mu Fn (eq 38)
    hmdns_integral_reset  as above, and s held at mu Fn / (8 G* a) while sliding (eq 40)

Every switch of the right-hand side (contact end, stick/slip entry and exit, HMD's
loading/unloading/reloading and full reversal, the eq 19 special case, the kinks of the
integral laws) is an event: the step that would cross it is shortened, by root finding on
the step itself, so that it ends on the switch and no step straddles one. Between switches
the right-hand side is smooth and an embedded Dormand-Prince 5(4) pair with error control
integrates it.

Switching choices (the rate-limit reading of the paper; see docs/laws.md "HMD implementation
choices" once written, which the engine follows):
- slip ends, for every capped law, when the elastic trial rate points back inside the
  Coulomb limit: sign * kt vs < mu Fn' (the test LS and HM make each step). For HMD this
  makes the "reverse when admissible" and "reverse at once" readings coincide in the limit
  of small steps; after slip HMD restarts on the unloading branch with Ft* = mu Fn if vs
  has reversed, else on the loading branch with theta = 1 (eq 19 special case);
- HMD's eq 19/24 special case: theta = 1 while eq 19 holds, kappa |vs| < mu u (the
  paper's eq 24 is garbled in the extraction); ``Impact.special_case`` selects when a
  special state entered there ends, as the engine's ``special_case`` parameter: 0 when
  eq 19 stops holding (default), 1-3 and 5 at an event where the reading's end condition
  (``_Law.special_margin``) reaches zero, 4 where the displacement deficit D reaches zero
  (docs/laws.md "HMD implementation choices", item 9);
- HMD's branch reversal (issue 13, ``Impact.partial_slip_reversal_check``, as the engine's
  parameter): the branch of direction D (+1 load/reload, -1 unload) reverses where D vs
  turns negative, except in partial slip (no special state) while Fn falls, where it
  reverses only once the new elastic branch is admissible: h = 8 G* a D vs - mu Fn'
  (divided by 2 E* a: kappa D v - mu u) crossing zero downwards; with 0, at D vs = 0;
- a full reversal at Ft = -Ft* needs Ft* > 0 (eq 23 drives Ft* below zero once Fn has
  fallen enough, and -Ft* is then no point of the mirrored curve; the engine's guard):
  it happens where the state enters {Ft <= -Ft*, Ft* > 0}, located by the continuous
  event function max(Ft + Ft*, -Ft*);
- a reload that climbs back to Ft* returns to the loading branch (at once if eq 23 has
  already taken Ft* below the force); an unload that reaches -Ft* is a full reversal:
  loading in the opposite direction;
- a dashpot (``Impact.restitution`` < 1, LS and HM): the engine's, derived again: Fn =
  max(kn delta + 2 zeta sqrt(m kn) u, 0) (LS) or max(K delta^1.5 + alpha sqrt(m K) delta^1/4 u,
  0) (HM, Tsuji et al. 1992, K = 4/3 E* sqrt(R)), the factor found here for the requested
  restitution by bisection on this solver's own normal impact (``damping_for``). The Coulomb
  limit is mu times that force, and the cap's rate Fn' includes the dashpot's. The
  contact starts sticking (the cap mu Fn grows as t^(1/4), or jumps, faster than any
  elastic trial) and ends where the force returns to zero, before the overlap has closed
  (then the sphere flies free: no force acts on it until the overlap is zero);
- LS kn is the paper's eq 28, kn = 1.2024 (m^1/2 E*^2 R V)^2/5 at the impact speed V
  (y1, y2, et of the linear law do not depend on kn: it only sets the time scale).
"""

from __future__ import annotations

import dataclasses
import math

LAWS = ("hmd", "hm", "ls", "lth", "hmdns_integral", "hmdns_integral_reset")
# the laws with a dashpot here (Impact.restitution < 1)
DAMPED_LAWS = ("hm", "ls")

# The paper's 30-angle sweep (deg): dense where the laws differ (below the ~30 deg onset of
# sliding throughout), sparse in gross sliding.
PAPER_ANGLES_DEG = (0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 12.0, 14.0, 16.0, 18.0,
                    20.0, 22.0, 25.0, 28.0, 30.0, 33.0, 36.0, 40.0, 45.0, 50.0, 55.0, 60.0, 70.0, 80.0, 85.0)


@dataclasses.dataclass(frozen=True)
class Impact:
    """The paper's problem (section 4); every field can be changed for limit checks."""

    law: str = "hmd"
    angle_deg: float = 30.0
    speed: float = 5.0  # m/s
    radius: float = 0.025  # m
    density: float = 2650.0  # kg/m3
    youngs_modulus: float = 70e9  # Pa, sphere and wall
    poisson_ratio: float = 0.3
    friction: float = 0.1
    stiffness_ratio: float | None = None  # LS only: kappa = kt/kn; default eq 10
    normal_stiffness: float | None = None  # LS only: kn; default eq 28
    special_case: int = 0  # HMD only: reading of eq 24, as the engine's hmd parameter
    # HMD only, as the engine's hmd parameter: 1 a reversal in partial slip while Fn falls
    # waits until it is admissible (issue 13), 0 at the velocity reversal
    partial_slip_reversal_check: int = 1
    # LS and HM only: the normal restitution their dashpot gives (1: none), or the
    # dashpot's factor itself (damping: zeta for LS, alpha for HM; restitution then ignored)
    restitution: float = 1.0
    damping: float | None = None

    @property
    def mass(self) -> float:
        return self.density * 4.0 / 3.0 * math.pi * self.radius**3

    @property
    def effective_modulus(self) -> float:  # eq 14, identical sphere and wall
        return self.youngs_modulus / (2.0 * (1.0 - self.poisson_ratio**2))

    @property
    def effective_shear_modulus(self) -> float:  # eq 20
        shear = self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))
        return shear / (2.0 * (2.0 - self.poisson_ratio))

    @property
    def kappa(self) -> float:  # eq 10
        nu = self.poisson_ratio
        return 2.0 * (1.0 - nu) / (2.0 - nu)

    @property
    def ls_normal_stiffness(self) -> float:  # eq 28
        if self.normal_stiffness is not None:
            return self.normal_stiffness
        return 1.2024 * (math.sqrt(self.mass) * self.effective_modulus**2 * self.radius * self.speed) ** 0.4


@dataclasses.dataclass
class Solution:
    impact: Impact
    en: float
    et: float
    x: float
    y1: float
    y2: float
    contact_duration: float  # s
    max_overlap: float  # m
    steps: int  # accepted Runge-Kutta steps
    rejected: int
    events: list  # (time s, description)

    def measures(self) -> dict:
        return {"en": self.en, "et": self.et, "x": self.x, "y1": self.y1, "y2": self.y2}


# state indices: S is the total tangential displacement, D the displacement deficit of
# special_case 4 (both HMD only)
DELTA, U, VT, WR, Q, F1, F2, S, D = range(9)
NSTATE = 9
# HMD's special state (the third item of a mode): off, on because eq 19 holds, on after
# eq 19 stopped holding until the reading's end condition (special_case 1-3), on while the
# deficit is positive (special_case 4), on until the normal force stops growing (5)
SPECIAL_OFF, SPECIAL_EQ19, SPECIAL_LATCHED, SPECIAL_DEFICIT = 0, 1, 2, 3

# Dormand-Prince 5(4) tableau
_C = (0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0)
_A = (
    (),
    (1 / 5,),
    (3 / 40, 9 / 40),
    (44 / 45, -56 / 15, 32 / 9),
    (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
    (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
    (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
)
_B5 = (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0.0)
_B4 = (5179 / 57600, 0.0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40)
_E = tuple(b5 - b4 for b5, b4 in zip(_B5, _B4))


class _Law:
    """Right-hand side, tangential force, events and transitions of one law.

    A mode is a tuple (kind, sign, flag, anchor), anchor the (S, Fn, Ft) where HMD's special
    state began (or None). Each event function is positive inside the mode
    and the event happens where it reaches zero; ``transition`` returns the new mode and
    state.
    """

    def __init__(self, impact: Impact):
        self.p = impact
        self.name = impact.law
        self.m = impact.mass
        self.R = impact.radius
        self.mu = impact.friction
        self.special_case = impact.special_case
        if self.special_case not in range(6):
            raise ValueError(f"reference: special_case must be 0..5, got {self.special_case!r}")
        self.admissible_reversal = impact.partial_slip_reversal_check
        if self.admissible_reversal not in (0, 1):
            raise ValueError("reference: partial_slip_reversal_check must be 0 or 1, "
                             f"got {self.admissible_reversal!r}")
        self.spin_factor = self.R**2 * self.m / (0.4 * self.m * self.R**2)  # m R^2 / I = 5/2
        e_star, g_star = impact.effective_modulus, impact.effective_shear_modulus
        self.linear = self.name == "ls"
        if self.linear:
            self.kn = impact.ls_normal_stiffness
            self.kappa = impact.stiffness_ratio if impact.stiffness_ratio is not None else impact.kappa
            self.kt = self.kappa * self.kn
        else:
            self.hertz = 4.0 / 3.0 * e_star * math.sqrt(self.R)  # Fn = hertz delta^1.5 (eq 15)
            self.shear = 8.0 * g_star  # kt = shear a (eq 29)
            self.kappa = 4.0 * g_star / e_star  # = eq 10
            self.e_star, self.g_star = e_star, g_star
        # the dashpot's coefficient: Fd = dashpot u (LS), dashpot delta^1/4 u (HM)
        self.dashpot = 0.0
        if impact.damping is not None or impact.restitution < 1.0:
            if self.name not in DAMPED_LAWS:
                raise ValueError(f"reference: a dashpot is modelled for {', '.join(DAMPED_LAWS)} only, "
                                 f"not {self.name!r}")
            factor = impact.damping if impact.damping is not None else damping_for(impact)
            if self.linear:
                self.dashpot = 2.0 * factor * math.sqrt(self.m * self.kn)
            else:
                self.dashpot = factor * math.sqrt(self.m * self.hertz)

    # -- normal contact -----------------------------------------------------------
    def normal(self, delta, u):
        """Fn and dFn/dt (the force is that of the overlap; zero overlap ends contact; a
        dashpot's force is clipped at zero, where the contact ends too)."""
        force, rate = self._elastic(delta, u)
        if not self.dashpot:
            return force, rate
        force = self.unclipped_force(delta, u)
        if force <= 0.0:
            return 0.0, 0.0
        acceleration = -force / self.m
        if self.linear:
            return force, rate + self.dashpot * acceleration
        d = max(delta, 0.0)
        quarter = math.sqrt(math.sqrt(d))
        # d/dt (delta^1/4 u) = delta^1/4 u' + u^2 / (4 delta^3/4): infinite at first touch,
        # where no event reads it (the contact sticks, and rhs integrates Fn' only in slip)
        spread = 0.25 * u * u / (quarter * quarter * quarter) if d > 0.0 else 0.0
        return force, rate + self.dashpot * (quarter * acceleration + spread)

    def _elastic(self, delta, u):
        """The spring's force and its rate."""
        d = max(delta, 0.0)
        if self.linear:
            return self.kn * d, self.kn * u
        root = math.sqrt(d)
        return self.hertz * d * root, 1.5 * self.hertz * root * u

    def unclipped_force(self, delta, u):
        """Spring and dashpot (LS: dashpot u, HM: dashpot delta^1/4 u), before the clip."""
        d = max(delta, 0.0)
        return self._elastic(d, u)[0] + self.dashpot * u * (1.0 if self.linear else math.sqrt(math.sqrt(d)))

    def shear_stiffness(self, delta):
        return self.kt if self.linear else self.shear * math.sqrt(self.R * max(delta, 0.0))

    # -- initial mode ---------------------------------------------------------------
    def initial(self, vni, vti):
        """Mode at first touch, from the ratio of tangential to normal rates at t -> 0."""
        mu, kappa, name = self.mu, self.kappa, self.name
        # ratio of the elastic tangential rate to mu times the normal one: kt vs / (kn u)
        # for LS, kappa vs / u for Hertz-Mindlin, 3/2 of it for the secant laws (eq 38)
        sliding_ratio = kappa * vti / vni * (1.5 if name.startswith("hmdns_integral") else 1.0)
        slides = vti > 0.0 and sliding_ratio > mu
        if self.dashpot and mu > 0.0:
            # the dashpot's force jumps (LS) or grows as t^(1/4) (HM) at first touch: the
            # Coulomb limit outgrows every elastic trial, the contact sticks
            slides = False
        if name == "hmd":
            if slides:
                return ("slide", 1.0, 0, None)
            # eq 19: theta = 1 while kappa vs < mu u
            if self.special_case == 4:
                return ("load", 1.0, SPECIAL_DEFICIT, None)
            return ("load", 1.0, SPECIAL_EQ19, (0.0, 0.0, 0.0))
        if name == "hmdns_integral":
            return ("capped", 1.0, 0, None) if slides else ("elastic", 0.0, 0, None)
        if name == "lth":
            return ("slide", 1.0, 0, None) if slides else ("stick", 1.0, 0, None)
        return ("slide", 1.0, 0, None) if slides else ("stick", 0.0, 0, None)

    # -- tangential force ---------------------------------------------------------
    def tangential(self, mode, y, fn):
        kind, sign = mode[:2]
        if kind in ("slide", "capped"):
            return sign * self.mu * fn
        name = self.name
        if name in ("ls", "hm", "hmd"):
            return y[Q]
        if name == "lth":
            s_star = self.mu * max(y[DELTA], 0.0) / self.kappa
            if s_star <= 0.0:
                return 0.0
            ratio = min(abs(y[Q]) / s_star, 1.0)
            return math.copysign(self.mu * fn * (1.0 - (1.0 - ratio) ** 1.5), y[Q])
        return self.shear_stiffness(y[DELTA]) * y[Q]  # integral laws, elastic

    def theta(self, mode, y, fn):
        kind, sign, special = mode[:3]
        if special or fn <= 0.0:
            return 1.0
        f = sign * y[Q]
        mu_fn = self.mu * fn
        if kind == "unload":
            cube = 1.0 - (y[F1] - f) / (2.0 * mu_fn)  # eq 22b
        elif kind == "reload":
            cube = 1.0 - (f - y[F2]) / (2.0 * mu_fn)  # eq 22c
        else:
            cube = 1.0 - f / mu_fn  # eq 22a
        return min(max(cube, 0.0), 1.0) ** (1.0 / 3.0)

    def rhs(self, mode, y):
        fn, dfn = self.normal(y[DELTA], y[U])
        ft = self.tangential(mode, y, fn)
        vs = y[VT] + y[WR]
        kind, sign = mode[:2]
        name = self.name
        dq = 0.0
        ds = dd = 0.0
        if name in ("ls", "hm"):
            dq = sign * self.mu * dfn if kind == "slide" else self.shear_stiffness(y[DELTA]) * vs
        elif name == "hmd":
            if kind == "slide":
                dq = sign * self.mu * dfn
            else:
                theta = self.theta(mode, y, fn)
                branch = -1.0 if kind == "unload" else 1.0
                dq = sign * (self.shear_stiffness(y[DELTA]) * theta * sign * vs
                             + branch * self.mu * dfn * (1.0 - theta))
            ds = vs
            if mode[2] == SPECIAL_DEFICIT:
                # mu Fn' / 8 G* a = mu u / kappa; |vs| is owed only while Fn grows
                dd = self.mu * y[U] / self.kappa - (abs(vs) if y[U] > 0.0 else 0.0)
        elif name == "lth":
            dq = vs
        elif name == "hmdns_integral_reset" and kind == "slide":
            dq = sign * self.mu * self.e_star * y[U] / (6.0 * self.g_star)  # d/dt of mu Fn / (8 G* a)
        else:
            dq = vs
        # Ft*, Ft** (eq 23) are HMD's: held constant for the other laws, whose dashpot
        # rate is infinite at first touch
        memory = self.mu * dfn if name == "hmd" else 0.0
        return (y[U], -fn / self.m, -ft / self.m, -self.spin_factor * ft / self.m, dq, memory, -memory, ds, dd)

    # -- events -------------------------------------------------------------------
    def events(self, mode, y):
        """[(g, label)]: g > 0 inside the mode; the first zero crossing triggers ``label``."""
        fn, dfn = self.normal(y[DELTA], y[U])
        kind, sign, special = mode[:3]
        vs = y[VT] + y[WR]
        mu_fn = self.mu * fn
        out = [(y[DELTA], "end"), (y[U], "max_overlap")]
        if self.dashpot:
            # the force returns to zero before the overlap closes: the sphere leaves
            out.append((self.unclipped_force(y[DELTA], y[U]), "end"))
        name = self.name
        if kind == "slide" or kind == "capped":
            if name in ("ls", "hm", "hmd"):
                # elastic trial rate back inside the cone: sign kt vs < mu Fn'
                if self.linear or self.dashpot:
                    out.append((sign * self.shear_stiffness(y[DELTA]) * vs - self.mu * dfn, "stick"))
                else:  # divided by 2 E* a: kappa vs sign < mu u
                    out.append((self.kappa * sign * vs - self.mu * y[U], "stick"))
            elif name == "lth":
                # back below the sliding displacement: |s| < s*
                out.append((sign * y[Q] - self.mu * max(y[DELTA], 0.0) / self.kappa, "stick"))
            elif name == "hmdns_integral_reset":
                out.append((sign * vs - self.mu * self.e_star * y[U] / (6.0 * self.g_star), "stick"))
            else:  # hmdns_integral capped: the secant force falls back under mu Fn
                out.append((sign * self.shear_stiffness(y[DELTA]) * y[Q] - mu_fn, "stick"))
            return out
        if name == "lth":
            s_star = self.mu * max(y[DELTA], 0.0) / self.kappa
            out += [(s_star - y[Q], "slide+"), (s_star + y[Q], "slide-"), (sign * y[Q], "zero")]
            return out
        ft = self.tangential(mode, y, fn)
        out += [(mu_fn - ft, "slide+"), (mu_fn + ft, "slide-")]
        if name == "hmd":
            v = sign * vs
            f = sign * y[Q]
            rate_gap = self.mu * y[U] - self.kappa * abs(v)  # eq 19 holds while > 0
            if special == SPECIAL_EQ19:
                out.append((rate_gap, "special"))
            elif special == SPECIAL_DEFICIT:
                out.append((y[D], "special_end"))
            else:
                out.append((-rate_gap, "special"))
            if special == SPECIAL_LATCHED:
                out.append((self.special_margin(mode, y, fn), "special_end"))
            # where the branch reverses: the surface velocity against the branch
            # direction, D v < 0; in partial slip while Fn falls (issue 13) only once the
            # reversed elastic branch is admissible, h = 8 G* a D vt - mu Fn' < 0 (divided
            # by 2 E* a: kappa D v - mu u). Both are positive inside the branch and change
            # sign together at u = 0 (the max_overlap event), so the event is continuous.
            direction = -1.0 if kind == "unload" else 1.0
            reversal = direction * v
            if self.admissible_reversal and special == SPECIAL_OFF and y[U] < 0.0:
                reversal = self.kappa * direction * v - self.mu * y[U]
            if kind == "load":
                out.append((reversal, "unload"))
            elif kind == "unload":
                # full reversal where the state enters {f <= -Ft*, Ft* > 0} (a reversal
                # point: eq 23 drives Ft* below zero once Fn has fallen enough, and -Ft*
                # is then no point of the mirrored curve). The set is entered through
                # f + Ft* = 0 or through Ft* = 0; each boundary is its own continuous
                # event and transition() checks the other condition there. (The old
                # single event, "f + Ft* if Ft* > 0 else 1", jumped to 1 when a step took
                # Ft* through zero just after f + Ft* had crossed it, so the reversal was
                # missed: et 0.845 instead of 0.750 at mu = 1, 1 deg. With fast eq 23
                # the set can be crossed within one step, so no single function of the
                # end points can locate it.)
                out += [(reversal, "reload"), (f + y[F1], "reverse"), (-y[F1], "reverse_point_positive")]
            else:
                out += [(reversal, "unload"), (y[F1] - f, "load")]
        return out

    def special_margin(self, mode, y, fn):
        """> 0 while a latched special state goes on (special_case 1, 2, 3, 5)."""
        if self.special_case == 5:
            return y[U]
        if self.special_case == 1:
            return self.mu * fn - self.shear_stiffness(y[DELTA]) * abs(y[S])
        s0, fn0, q0 = mode[3]
        if self.special_case == 2:
            return self.mu * (fn - fn0) - abs(y[Q] - q0)
        return self.mu * (fn - fn0) - self.shear_stiffness(y[DELTA]) * abs(y[S] - s0)

    def _enter(self, y, fn):
        """Special state where eq 19 starts to hold, with its anchor."""
        if self.special_case == 4:
            return SPECIAL_DEFICIT, None
        return SPECIAL_EQ19, (y[S], fn, y[Q])

    def _special(self, y, sign, mode=None):
        """Special state after a branch switch: eq 19 now, or a state that goes on."""
        fn, _ = self.normal(y[DELTA], y[U])
        eq19 = self.mu * y[U] - self.kappa * abs(y[VT] + y[WR]) > 0.0
        old = SPECIAL_OFF if mode is None else mode[2]
        if old == SPECIAL_DEFICIT:
            return old, None
        if eq19:
            return (SPECIAL_EQ19, mode[3]) if old != SPECIAL_OFF else self._enter(y, fn)
        if old != SPECIAL_OFF and self.special_case != 0 and self.special_margin(mode, y, fn) > 0.0:
            return SPECIAL_LATCHED, mode[3]
        return SPECIAL_OFF, None

    def transition(self, mode, y, label):
        kind, sign, special = mode[:3]
        y = list(y)
        fn, dfn = self.normal(y[DELTA], y[U])
        vs = y[VT] + y[WR]
        name = self.name
        if label == "max_overlap":
            return mode, y
        if label in ("slide+", "slide-"):
            new_sign = 1.0 if label == "slide+" else -1.0
            if name == "hmdns_integral":
                return ("capped", new_sign, 0, None), y
            if name == "lth":
                return ("slide", new_sign, 0, None), y
            if name == "hmdns_integral_reset":
                y[Q] = new_sign * self.mu * self.e_star * max(y[DELTA], 0.0) / (6.0 * self.g_star)
            else:
                y[Q] = new_sign * self.mu * fn
            y[D] = 0.0  # on the Coulomb limit the force is on every curve
            return ("slide", new_sign, 0, None), y
        if label == "stick":
            if name == "hmdns_integral":
                return ("elastic", 0.0, 0, None), y
            if name == "hmd":
                y[Q] = sign * self.mu * fn
                y[F1], y[F2] = self.mu * fn, -self.mu * fn
                if sign * vs < 0.0:
                    return ("unload", sign, *self._special(y, sign)), y
                # slip ends where the trial rate is back inside the cone: eq 19 holds
                return ("load", sign, *self._enter(y, fn)), y
            if name == "lth":
                return ("stick", sign, 0, None), y  # q = sign s* already
            if name == "hmdns_integral_reset":
                return ("stick", 0.0, 0, None), y
            y[Q] = sign * self.mu * fn
            return ("stick", 0.0, 0, None), y
        if label == "zero":
            return (kind, -sign, special, mode[3]), y
        if label == "special":
            if special == SPECIAL_OFF:
                return (kind, sign, *self._enter(y, fn)), y
            if special == SPECIAL_LATCHED:  # eq 19 holds again: the state goes on
                return (kind, sign, SPECIAL_EQ19, mode[3]), y
            # eq 19 stops holding: the reading's end condition decides (0: at once)
            if self.special_case != 0 and self.special_margin(mode, y, fn) > 0.0:
                return (kind, sign, SPECIAL_LATCHED, mode[3]), y
            return (kind, sign, SPECIAL_OFF, None), y
        if label == "special_end":
            y[D] = 0.0
            if name == "hmd" and abs(y[Q]) >= self.mu * fn * (1.0 - 1e-9):
                # special_case 2 from a zero anchor ends exactly on the Coulomb limit
                return self.transition(mode, y, "slide+" if y[Q] > 0.0 else "slide-")
            return (kind, sign, SPECIAL_OFF, None), y
        if label == "unload":
            y[F1] = sign * y[Q]
            return ("unload", sign, *self._special(y, sign, mode)), y
        if label == "reload":
            y[F2] = sign * y[Q]
            if sign * y[Q] >= y[F1]:
                # eq 23 has taken Ft* below the force: the reload is already past Ft*,
                # so the memory is erased at once (the engine's test, made each step)
                return ("load", sign, *self._special(y, sign, mode)), y
            return ("reload", sign, *self._special(y, sign, mode)), y
        if label == "load":
            return ("load", sign, *self._special(y, sign, mode)), y
        if label in ("reverse", "reverse_point_positive"):
            f = sign * y[Q]
            if y[F1] > 0.0 and f + y[F1] <= 0.0:
                return ("load", -sign, *self._special(y, -sign, mode)), y
            return mode, y  # the other boundary of the set: no reversal
        raise AssertionError(label)


def _step(law, mode, y, h):
    k = []
    for i in range(7):
        if i == 0:
            yi = y
        else:
            a = _A[i]
            yi = [y[j] + h * sum(a[s] * k[s][j] for s in range(i)) for j in range(NSTATE)]
        k.append(law.rhs(mode, yi))
    y_new = [y[j] + h * sum(_B5[s] * k[s][j] for s in range(7)) for j in range(NSTATE)]
    err = [h * sum(_E[s] * k[s][j] for s in range(7)) for j in range(NSTATE)]
    return y_new, err


def solve(impact: Impact, rtol: float = 1e-10, max_steps: int = 200_000) -> Solution:
    """Integrate one impact from first touch to separation; ``rtol`` relative to the
    natural scale of each variable (max overlap, impact speed, mu times the peak force)."""
    if impact.law not in LAWS:
        raise ValueError(f"reference: unknown law {impact.law!r}; known: {', '.join(LAWS)}")
    law = _Law(impact)
    angle = math.radians(impact.angle_deg)
    vni, vti = impact.speed * math.cos(angle), impact.speed * math.sin(angle)
    m = impact.mass
    # scales: Hertz (or linear) maximum overlap and force at the full speed
    if law.linear:
        delta_scale = impact.speed * math.sqrt(m / law.kn)
        force_scale = law.kn * delta_scale
    else:
        delta_scale = (15.0 * m * impact.speed**2 / (16.0 * math.sqrt(impact.radius) * impact.effective_modulus)) ** 0.4
        force_scale = law.hertz * delta_scale**1.5
    time_scale = delta_scale / impact.speed
    mu_scale = max(impact.friction, 1e-3)
    q_scale = mu_scale * (delta_scale if impact.law in ("lth", "hmdns_integral", "hmdns_integral_reset")
                          else force_scale)
    scale = (delta_scale, impact.speed, impact.speed, impact.speed, q_scale, mu_scale * force_scale,
             mu_scale * force_scale, mu_scale * delta_scale, mu_scale * delta_scale)
    t_tol = 1e-15 * time_scale

    mode = law.initial(vni, vti)
    y = [0.0, vni, vti, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    t, h = 0.0, 1e-4 * time_scale * rtol ** 0.2
    steps = rejected = 0
    events = [(0.0, f"start in {mode[0]}")]
    max_overlap = 0.0
    while True:
        if steps + rejected > max_steps:
            raise RuntimeError(f"reference: no separation after {max_steps} steps ({impact})")
        y_new, err = _step(law, mode, y, h)
        norm = max(abs(e) / (rtol * max(abs(a), abs(b), s)) for e, a, b, s in zip(err, y, y_new, scale))
        if norm > 1.0:
            rejected += 1
            h *= max(0.2, 0.9 * norm ** -0.2)
            continue
        g0 = law.events(mode, y)
        g1 = law.events(mode, y_new)
        crossed = [i for i, ((a, _), (b, _)) in enumerate(zip(g0, g1)) if a > 0.0 and b <= 0.0]
        label = None
        if crossed:
            # earliest event: root of g(step(y, h_e)) on (0, h], Illinois regula falsi
            best_h, best = h, None
            for i in crossed:
                lo, glo, hi, ghi = 0.0, g0[i][0], h, g1[i][0]
                side = 0
                for _ in range(200):
                    if hi - lo <= t_tol:
                        break
                    mid = (lo * ghi - hi * glo) / (ghi - glo)
                    if not lo < mid < hi:
                        mid = 0.5 * (lo + hi)
                    gm = law.events(mode, _step(law, mode, y, mid)[0])[i][0]
                    if gm > 0.0:
                        lo, glo = mid, gm
                        if side == 1:
                            ghi *= 0.5
                        side = 1
                    else:
                        hi, ghi = mid, gm
                        if side == -1:
                            glo *= 0.5
                        side = -1
                    if gm == 0.0:
                        break
                if hi <= best_h:
                    best_h, best = hi, i
            if best_h < h:
                y_new, _ = _step(law, mode, y, best_h)
            h_taken, label = best_h, g0[best][1]
        else:
            h_taken = h
        t += h_taken
        y = y_new
        steps += 1
        max_overlap = max(max_overlap, y[DELTA])
        if label is not None:
            if label == "end":
                events.append((t, label))
                break
            new_mode, y = law.transition(mode, y, label)
            if label.startswith("reverse"):
                # a boundary of the full-reversal set where the other condition fails
                label = "reverse" if new_mode[1] != mode[1] else "no reversal (Ft* <= 0)"
            events.append((t, label))
            mode = new_mode
        else:
            h *= min(5.0, max(0.2, 0.9 * max(norm, 1e-10) ** -0.2))
    vs = y[VT] + y[WR]
    en = -y[U] / vni
    scale_out = (1.0 + en) * vni
    return Solution(
        impact=impact, en=en, et=y[VT] / vti if vti > 0.0 else math.nan,
        x=2.0 * math.tan(angle) / (1.0 + en), y1=2.0 * vs / scale_out, y2=2.0 * y[WR] / scale_out,
        contact_duration=t, max_overlap=max_overlap, steps=steps, rejected=rejected, events=events,
    )


_DAMPING = {}


def damping_for(impact: Impact) -> float:
    """The dashpot factor (zeta for LS, alpha for HM) with which this solver's normal
    impact rebounds at ``impact.restitution``: bisection, the restitution falling from 1
    as the factor grows. It depends on the restitution alone (scaling lengths and times
    out of either equation leaves only the factor), so it is found once per law kind and
    restitution."""
    if not 0.0 < impact.restitution <= 1.0:
        raise ValueError(f"reference: restitution must be in (0, 1], got {impact.restitution!r}")
    key = (impact.law == "ls", impact.restitution)
    if key not in _DAMPING:
        def rebound(factor):
            return solve(dataclasses.replace(impact, angle_deg=0.0, friction=0.0, damping=factor), 1e-12).en

        low, high = 0.0, 1.0
        while rebound(high) > impact.restitution:
            low, high = high, 2.0 * high
        for _ in range(48):
            middle = 0.5 * (low + high)
            low, high = (middle, high) if rebound(middle) > impact.restitution else (low, middle)
        _DAMPING[key] = 0.5 * (low + high)
    return _DAMPING[key]


def sweep(laws=LAWS, angles=PAPER_ANGLES_DEG, rtol: float = 1e-10, **impact) -> dict:
    """{(law, angle): Solution} for the paper's sweep."""
    return {(law, a): solve(Impact(law=law, angle_deg=a, **impact), rtol) for law in laws for a in angles}
