"""PN-informed guidance: the paper's section IV in pure numpy (no I/O, no state, no asyncio).

Frames: world W is ENU-like with z up and ``g = [0, 0, -G]``; body B is FLU (x = optical
axis, z = thrust axis). Thrust ``f_th`` is mass-normalised (m/s^2) throughout, as in the
paper's simplified problem. Names follow the paper's symbols:

=====================================  ==========================================
paper                                   here
=====================================  ==========================================
lambda_dot = f_est arccos(l . l_prev)   :func:`los_rate` -> ``lambda_dot``
k_l = l x l_prev,  n = l x k_l          :func:`los_rate` -> ``k_l``, ``n``
eq:meth_pn_guidance_law (a_n)           :func:`pn_demand`
k_PN, v_rel_bar, gamma_bar              ``GuidanceParams.k_pn``, ``.v_rel_bar``, ``.gamma_bar``
f_th upper limit (bar f_th)             ``GuidanceParams.f_max`` (and ``.f_min``, the thrust floor)
(not in the paper) maximum tilt         ``GuidanceParams.max_tilt`` (thrust axis from vertical)
eq:meth_rotation_pn_world (R_PN^W)      :func:`pn_frame`
eq:meth_optimization_problem_roll_pitch :func:`roll_pitch`, :func:`angles_of_thrust`
f_th*, phi*, theta* (closed form)       :func:`solve` (as a tuple: :func:`solve_fields`)
saturation of infeasible demands        :func:`demand_scale`
R_B^W = R_PN^W R_y(phi) R_x(theta)      :func:`solve` -> ``R_W_B``
MAVSDK setpoint (NED/FRD, deg, 0..1)    :func:`to_setpoint`
=====================================  ==========================================

The problem in thrust coordinates. In the PN frame the thrust vector is
``t = f R_y(phi) R_x(theta) e_z = f [sin(phi) cos(theta), -sin(theta), cos(phi) cos(theta)]``. The PN law fixes
its components normal to the LOS, ``(t_y, t_z) = s (n_y a_n, n_z a_n) - (g_y^PN, g_z^PN)`` (s = 1: the demand
in full), and the paper's objective ``f sin(phi) cos(theta)`` is ``t_x``, the thrust along the LOS. The
envelope, every constraint convex in ``(t_x, s)``:

(a) thrust floor ``t_z >= f_min`` (implies ``f >= f_min``; it also keeps ``cos(phi) cos(theta) = t_z / f``
    away from 0: no knife edge about the LOS);
(b) ``|t| <= f_max``;
(c) field of view. ``fov="exact"`` (default) bounds the real angle between the optical axis
    ``R_y(phi) e_x`` and the LOS, which is ``|phi|`` (roll turns the vehicle about the LOS):
    ``|t_x| <= t_z tan(gamma_bar)``. ``fov="paper"`` keeps the paper's ``cos(phi) cos(theta) >= cos(gamma_bar)``,
    i.e. ``t_x^2 + t_y^2 <= (t_z tan(gamma_bar))^2``, stricter: it caps sideways acceleration at
    ``g tan(gamma_bar)``. A camera pitched up by ``uptilt`` mu (exact mode only) has the optical axis
    ``cos(mu) x_B + sin(mu) z_B``: ``cos(mu) t_z / hypot(t_x, t_z) + sin(mu) t_x / |t| >= cos(gamma_bar)``,
    one or two intervals of ``t_x`` found by root finding (:func:`_uptilt_pieces`; docs/guidance.md "Camera uptilt");
(d) flight envelope: the thrust axis at most ``max_tilt`` from vertical, ``u . t >= cos(max_tilt) |t|`` with
    ``u`` world up in the PN frame (a second-order cone). Together with (a) this excludes the knife-edge
    setpoints (roll +-90 deg at low thrust) the solver used to produce.

``t_x*`` is the largest ``t_x`` that (a)-(d) allow (:func:`_best_tx`; without (d) it is the paper's closed form).
``phi = atan2(t_x, t_z)`` and ``theta = atan2(-t_y, hypot(t_x, t_z))`` recover the attitude without the
rounding of an arccos of tiny ratios, so the FOV bound holds to machine precision.

Saturation rule (the paper leaves infeasible demands open): the largest ``s`` in [0, 1] for which (a)-(d)
have a solution. The constraints are convex in ``(t_x, s)``, so the feasible scales form an interval: the
normal demand keeps its direction and is scaled down just enough (closed form for (a)-(c), bisection when
the tilt cone binds). If even ``s = 0`` is infeasible (a LOS steeper than the FOV and tilt bounds together
allow, or one too steep for the thrust floor), the FOV bound gives way to the envelope: wings level about
the LOS, the optical axis as close to the LOS as ``max_tilt`` allows, thrust for level flight (``fallback``).
"""

from __future__ import annotations

import itertools
import math
import struct
from dataclasses import dataclass

import numpy as np

from companion.frames import euler_ned_deg_of, quat_wxyz_from_R
from perception.fastinit import fast_init

G = 9.81
DEFAULT_MAX_TILT_DEG = 50.0  # airframe.max_tilt default (x500: level flight at 50 deg needs 1.56 g of its 2 g)
g_W = np.array([0.0, 0.0, -G])

_EPS = 1e-12
# On the per-frame path a max/min of two floats is written ``b if b > a else a`` (= max(a, b)) and
# ``b if b < a else a`` (= min(a, b)): the same value in every case (ties, signed zeros, NaN: the builtins keep
# the first argument unless a later one is strictly greater / smaller), at a tenth of the builtin's ~0.09 us.
Vec3 = np.ndarray | tuple[float, float, float]  # a 3-vector: an array, or three floats on the per-frame path
_UPTILT_EPS = 1e-12  # rad: below, the camera counts as along body x (the closed form; subnormal sines underflow)
_ENU_TO_NED_ROWS = [1, 0, 2]
_F64 = np.dtype(np.float64)
_PACK_2X3X3 = struct.Struct("18d")  # eighteen native doubles: a (2, 3, 3) float64 array's bytes
_NED_FRD_SIGNS = np.outer([1.0, 1.0, -1.0], [1.0, -1.0, -1.0])  # row signs of P_NED_ENU x column signs of F_FRD_FLU


@fast_init  # built every simulated frame (the hover estimate's thrust limits): its __post_init__ still validates
@dataclass(frozen=True, slots=True)
class GuidanceParams:
    """Everything the solver needs. Angles in radians, thrusts mass-normalised (m/s^2)."""

    k_pn: float
    v_rel_bar: float
    gamma_bar: float
    f_max: float
    f_min: float
    fov: str = "exact"  # "exact": bound the real LOS-to-optical-axis angle; "paper": cos(phi) cos(theta)
    max_tilt: float = math.radians(DEFAULT_MAX_TILT_DEG)  # thrust axis from vertical, rad
    uptilt: float = 0.0  # camera pitched up about body y, rad: optical axis cos(mu) x_B + sin(mu) z_B (exact FOV only)

    def __post_init__(self) -> None:
        if self.fov not in ("exact", "paper"):
            raise ValueError(f"fov must be 'exact' or 'paper', got {self.fov!r}")
        if not (-math.pi / 2 < self.uptilt < math.pi / 2):
            raise ValueError(f"uptilt must be in (-pi/2, pi/2) rad, got {self.uptilt}")
        if self.uptilt != 0.0 and self.fov != "exact":
            raise ValueError("uptilt needs fov='exact' (the paper's bound takes a tilted camera as smaller gamma_bar)")
        if not (0.0 < self.gamma_bar < math.pi / 2):
            raise ValueError(f"gamma_bar must be in (0, pi/2) rad, got {self.gamma_bar}")
        if not (0.0 < self.max_tilt < math.pi / 2):
            raise ValueError(f"max_tilt must be in (0, pi/2) rad, got {self.max_tilt}")
        if not (0.0 < self.f_min < self.f_max):
            raise ValueError(f"need 0 < f_min < f_max, got f_min={self.f_min}, f_max={self.f_max}")


@dataclass(frozen=True, slots=True)
class LosRate:
    lambda_dot: float  # rad/s, >= 0
    k_l: np.ndarray  # l x l_prev (not normalised, as in the paper)
    n: np.ndarray  # unit normal direction of the PN acceleration; zero when lambda_dot == 0


@fast_init
@dataclass(frozen=True, slots=True)
class ThrustAttitude:
    f_th: float  # mass-normalised thrust, m/s^2
    phi: float  # pitch about PN y, rad
    theta: float  # roll about PN x, rad
    R_W_B: np.ndarray  # commanded attitude, body FLU -> world
    demand_scale: float  # s in [0, 1]: 1 = PN demand met exactly
    fallback: bool  # True when even s = 0 was infeasible (optical axis as near the LOS as the tilt bound allows)


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two vectors (arrays or float triples), accurate for small and large angles alike."""
    ax, ay, az = a.tolist() if isinstance(a, np.ndarray) else a
    bx, by, bz = b.tolist() if isinstance(b, np.ndarray) else b
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    return math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)


def los_rate(l: np.ndarray, l_prev: np.ndarray | None, dt: float) -> LosRate:  # noqa: E741
    """Inertial LOS rate from two consecutive world-frame unit LOS vectors, ``dt`` apart.

    ``lambda_dot = arccos(l . l_prev) / dt`` (the paper's ``f_est = 1/dt``), computed as
    ``atan2(|l x l_prev|, l . l_prev)`` which is exact for small angles where arccos is not.
    """
    if l_prev is None or not (dt > 0.0) or not math.isfinite(dt):
        return LosRate(0.0, np.zeros(3), np.zeros(3))
    # Scalar math: numpy's per-call overhead on 3-vectors dominates this 30 Hz path.
    lx, ly, lz = l.tolist()
    px, py, pz = l_prev.tolist()
    kx, ky, kz = ly * pz - lz * py, lz * px - lx * pz, lx * py - ly * px  # k_l = l x l_prev
    s = math.sqrt(kx * kx + ky * ky + kz * kz)
    if s < _EPS:
        return LosRate(0.0, np.array([kx, ky, kz]), np.zeros(3))
    angle = math.atan2(s, lx * px + ly * py + lz * pz)
    # n = l x k_l / |k_l|: |l x k_l| = |k_l| because k_l is normal to the unit vector l.
    n = np.array([ly * kz - lz * ky, lz * kx - lx * kz, lx * ky - ly * kx]) / s
    return LosRate(angle / dt, np.array([kx, ky, kz]), n)


def los_rate_vector(l: Vec3, l_prev: Vec3 | None, dt: float) -> tuple[float, float, float]:  # noqa: E741
    """``lambda_dot * n`` of :func:`los_rate` as three floats, the same operations bit for bit (the controller's
    per-frame path: no LosRate and no arrays; ``l`` and ``l_prev`` arrays or float triples)."""
    if l_prev is None or not (dt > 0.0) or not math.isfinite(dt):
        return 0.0, 0.0, 0.0
    lx, ly, lz = l.tolist() if isinstance(l, np.ndarray) else l
    px, py, pz = l_prev.tolist() if isinstance(l_prev, np.ndarray) else l_prev
    kx, ky, kz = ly * pz - lz * py, lz * px - lx * pz, lx * py - ly * px
    s = math.sqrt(kx * kx + ky * ky + kz * kz)
    if s < _EPS:
        return 0.0, 0.0, 0.0
    lam = math.atan2(s, lx * px + ly * py + lz * pz) / dt
    return (lam * ((ly * kz - lz * ky) / s), lam * ((lz * kx - lx * kz) / s), lam * ((lx * ky - ly * kx) / s))


def with_gamma_bar(p: GuidanceParams, gamma_bar: float) -> GuidanceParams:
    """``dataclasses.replace(p, gamma_bar=gamma_bar)`` without its per-call cost (the ring-in-view bound changes
    it every frame); the same validation of the new value."""
    if not (0.0 < gamma_bar < math.pi / 2):
        raise ValueError(f"gamma_bar must be in (0, pi/2) rad, got {gamma_bar}")
    q = object.__new__(GuidanceParams)
    for name in GuidanceParams.__slots__:
        object.__setattr__(q, name, gamma_bar if name == "gamma_bar" else getattr(p, name))
    return q


def pn_demand(lambda_dot: float, n: np.ndarray | tuple[float, float, float], k_pn: float,
              v_rel_bar: float) -> np.ndarray:
    """eq:meth_pn_guidance_law: ``a_n = k_PN * v_rel_bar * lambda_dot * n`` (``n`` an array or three floats)."""
    return np.array(pn_demand_xyz(lambda_dot, n, k_pn, v_rel_bar))


def pn_demand_xyz(lambda_dot: float, n: Vec3, k_pn: float, v_rel_bar: float) -> tuple[float, float, float]:
    """:func:`pn_demand` as three floats (the array product's values, without its cost)."""
    g = k_pn * v_rel_bar * lambda_dot
    nx, ny, nz = n.tolist() if isinstance(n, np.ndarray) else n
    return g * nx, g * ny, g * nz


def pn_frame(l: np.ndarray, y_ref: np.ndarray | None = None) -> np.ndarray:  # noqa: E741
    """eq:meth_rotation_pn_world: ``R_PN^W = [l, e_z x l, l x (e_z x l)]`` with unit columns.

    Singular when the LOS is vertical (``e_z x l = 0``): then the y axis is taken from
    ``y_ref`` (default world y) made normal to ``l``, so the frame stays orthonormal.
    """
    return np.array(_pn_frame_rows(l, y_ref))


def _pn_frame_rows(l: Vec3, y_ref: np.ndarray | None = None) -> list[list[float]]:  # noqa: E741
    """:func:`pn_frame` as nested lists of floats (rows), for the solver's scalar math (``l`` an array or floats)."""
    lx, ly, lz = l.tolist() if isinstance(l, np.ndarray) else l
    ny = math.hypot(lx, ly)
    if ny > 1e-9:
        yx, yy, yz = -ly / ny, lx / ny, 0.0  # e_z x l, normalised
    else:
        rx, ry, rz = (0.0, 1.0, 0.0) if y_ref is None else np.asarray(y_ref, dtype=float).tolist()
        d = rx * lx + ry * ly + rz * lz
        yx, yy, yz = rx - d * lx, ry - d * ly, rz - d * lz
        n = math.sqrt(yx * yx + yy * yy + yz * yz)
        if n < 1e-9:  # y_ref parallel to l: any normal will do
            yx, yy, yz = 1.0 - lx * lx, -lx * ly, -lx * lz
            n = math.sqrt(yx * yx + yy * yy + yz * yz)
        yx, yy, yz = yx / n, yy / n, yz / n
    zx, zy, zz = ly * yz - lz * yy, lz * yx - lx * yz, lx * yy - ly * yx  # l x y
    return [[lx, yx, zx], [ly, yy, zy], [lz, yz, zz]]


def roll_pitch(f_th: float, t_y: float, t_z: float) -> tuple[float, float]:
    """eq:meth_optimization_problem_roll_pitch for thrust components ``t = (t_y, t_z)`` normal to the LOS.

    ``t_y = n_y a_n - g_y^PN`` and ``t_z = n_z a_n - g_z^PN`` (the paper has ``g_y^PN = 0``).
    Returns (theta, phi). Arguments are clipped to [-1, 1] against rounding only: callers
    pass feasible inputs. :func:`solve` uses the equivalent, rounding-proof :func:`angles_of_thrust`.
    """
    theta = math.asin(max(-1.0, min(1.0, -t_y / f_th)))
    c = math.sqrt(max(f_th * f_th - t_y * t_y, 0.0))
    phi = math.acos(max(-1.0, min(1.0, t_z / c))) if c > _EPS else 0.0
    return theta, phi


def angles_of_thrust(t_x: float, t_y: float, t_z: float) -> tuple[float, float, float]:
    """(f_th, theta, phi) with ``f_th R_y(phi) R_x(theta) e_z = t`` (PN frame).

    ``R_y(phi) R_x(theta) e_z = [sin(phi) cos(theta), -sin(theta), cos(phi) cos(theta)]``, so
    ``phi = atan2(t_x, t_z)`` and ``theta = atan2(-t_y, hypot(t_x, t_z))``: no arccos of a ratio of
    two tiny numbers (the old exact-FOV bug: t_z ~ 1e-8 made phi pure rounding, 48.8 deg off the LOS).
    """
    c = math.hypot(t_x, t_z)
    return math.sqrt(c * c + t_y * t_y), math.atan2(-t_y, c), math.atan2(t_x, t_z)


def _tilt_margin(t_x: float, b: float, K: float, u_x: float, c: float) -> float:
    """``u . t - cos(max_tilt) |t|`` for ``t = (t_x, t_y, t_z)``, ``b = u_y t_y + u_z t_z``, ``K = t_y^2 + t_z^2``."""
    return u_x * t_x + b - c * math.sqrt(t_x * t_x + K)


def _envelope(t_y: float, t_z: float, u: tuple[float, float, float], p: GuidanceParams
              ) -> tuple[list[tuple[float, float]], float, float, float, float, float] | None:
    """(pieces, xm, b, K, u_x, c) for fixed normal thrust components, or None when (a)-(c) admit no ``t_x``.

    (a)-(c) of the module docstring allow ``t_x`` in the union of the intervals ``pieces`` (ascending; one,
    ``[-H, H]``, without uptilt); the tilt margin ``h(t_x) = u . t - cos(max_tilt) |t|`` is concave in ``t_x``
    with maximiser ``xm``: (d) is satisfiable in a piece iff h at ``xm`` clamped into it is >= 0.
    """
    # Tolerance on the scale of the thrusts involved, not of f_min alone: t_z = s a_z - g_z carries rounding
    # of ~1e-16 g, which a tiny f_min (thrust_min 1e-5) would turn into "no thrust allowed" at its own bound.
    if t_z < p.f_min - 1e-12 * p.f_max:
        return None
    K = t_y * t_y + t_z * t_z
    r2 = p.f_max * p.f_max - K
    if r2 < -1e-12 * p.f_max * p.f_max:
        return None
    r = math.sqrt(0.0 if r2 < 0.0 else r2)  # max(r2, 0.0)
    if abs(p.uptilt) > _UPTILT_EPS:
        pieces = [(max(-r, lo), min(r, hi)) for lo, hi in _uptilt_pieces(t_y, t_z, p.uptilt, p.gamma_bar)]
        pieces = [(lo, hi) for lo, hi in pieces if lo <= hi]
        if not pieces:
            return None
    else:
        w = _fov_width(t_y, t_z, K, p)
        if w is None:
            return None
        H = r if r < w else w  # min(w, r)
        pieces = [(-H, H)]
    u_x, u_y, u_z = u
    c = math.cos(p.max_tilt)
    s2 = c * c - u_x * u_x
    # Maximiser of h: finite when the LOS direction lies outside the tilt cone, else at +-inf.
    xm = u_x * math.sqrt(K / s2) if s2 > 1e-15 else (math.copysign(math.inf, u_x) if u_x != 0.0 else 0.0)
    return pieces, xm, u_y * t_y + u_z * t_z, K, u_x, c


def _fov_width(t_y: float, t_z: float, K: float, p: GuidanceParams) -> float | None:
    """The largest ``|t_x|`` the FOV bound (c) allows without uptilt, or None when it allows none (``K`` =
    ``t_y^2 + t_z^2``)."""
    tg = math.tan(p.gamma_bar)
    if p.fov == "exact":
        return t_z * tg
    w2 = t_z * t_z * tg * tg - t_y * t_y
    if w2 < -1e-12 * (1.0 + K):
        return None
    return math.sqrt(0.0 if w2 < 0.0 else w2)  # max(w2, 0.0)


def _uptilt_pieces(t_y: float, t_z: float, mu: float, gamma_bar: float) -> list[tuple[float, float]]:
    """The ``t_x`` allowed by the exact FOV bound (c) with the camera pitched up by ``mu``: ascending intervals.

    Optical axis ``o = cos(mu) x_B + sin(mu) z_B``; in the PN frame ``x_B = (cos phi, 0, -sin phi)`` and
    ``z_B = t / |t|``, so with ``u = t_x / t_z`` and ``k = (t_y^2 + t_z^2) / t_z^2 >= 1``
    ``F(u) = o . l - cos(gamma_bar) = cos(mu) / sqrt(1 + u^2) + sin(mu) u / sqrt(u^2 + k) - cos(gamma_bar) >= 0``.
    For mu > 0 (mu < 0 mirrors u) F rises on u <= 0. F' = 0 where ``G(u) = u ((u^2 + k) / (1 + u^2))^1.5 =
    tan(mu) k``; G is monotone between the roots of ``w^2 + (4 - 2k) w + k`` (w = u^2), which exist for k > 4
    (``|t_y| > sqrt(3) t_z``): at most three critical points, one per monotone piece of G. F is monotone between
    them, so the set F >= 0 (one or two intervals) follows exactly; roots by safeguarded Newton
    (:func:`_monotone_root`), each end moved to the feasible side.
    """
    cm, sm, cg = math.cos(mu), math.sin(abs(mu)), math.cos(gamma_bar)
    k = 1.0 + (t_y / t_z) ** 2

    def F(x: float) -> float:
        return cm / math.sqrt(1.0 + x * x) + sm * x / math.sqrt(x * x + k) - cg

    def dF(x: float) -> float:
        return sm * k / (x * x + k) ** 1.5 - cm * x / (1.0 + x * x) ** 1.5

    def d2F(x: float) -> float:
        return -cm * (1.0 - 2.0 * x * x) / (1.0 + x * x) ** 2.5 - 3.0 * sm * k * x / (x * x + k) ** 2.5

    def root(f, out: float, ins: float, guess: float) -> float:  # f(out) < 0 <= f(ins): root, on the feasible side
        x = _monotone_root(f, dF, out, ins, guess)
        step = 1e-16 * (1.0 + abs(x))
        while f(x) < 0.0:
            x, step = x + math.copysign(step, ins - out), 2.0 * step
            if (ins - x) * (ins - out) <= 0.0:
                return ins
        return x

    a = -math.sqrt(max((cm / cg) ** 2 - 1.0, 0.0)) - 1e-9  # below a: F < cos(mu) / sqrt(1 + u^2) - cg <= 0
    b = math.inf if sm >= cg else math.sqrt(max((cm / (cg - sm)) ** 2 - 1.0, 0.0)) * (1.0 + 1e-9) + 1e-9
    g_lo, g_hi = math.tan(max(abs(mu) - gamma_bar, -1.5)), math.tan(min(abs(mu) + gamma_bar, 1.5))  # k = 1 roots
    if k <= 4.0 and b < math.inf and F(0.0) >= 0.0:  # the common case: one maximum, F(a) < 0 <= F(0), F(b) < 0
        lo, hi = root(F, a, 0.0, g_lo), root(F, b, 0.0, g_hi)
        return [(lo * t_z, hi * t_z)] if mu > 0.0 else [(-hi * t_z, -lo * t_z)]
    # Critical points of F on u > 0. dF > 0 at 0, dF < 0 beyond tan(mu) k (there (u^2 + k) / (1 + u^2) >= 1).
    edges = [0.0]
    if k > 4.0:
        d = math.sqrt((k - 1.0) * (k - 4.0))
        edges += [math.sqrt(k - 2.0 - d), math.sqrt(k - 2.0 + d)]
    edges.append(max(math.tan(abs(mu)) * k * (1.0 + 1e-9) + 1e-12, 2.0 * edges[-1]))
    crit = []
    for lo, hi in itertools.pairwise(edges):
        dlo, dhi = dF(lo), dF(hi)
        if dlo == 0.0:
            crit.append(lo)
        elif dlo * dhi < 0.0:
            crit.append(_monotone_root(dF, d2F, lo, hi, math.tan(abs(mu))))  # tan(mu): u* without roll (k = 1)
    # Nodes between which F is monotone: a, the critical points, b. Beyond b F < cos(mu) / sqrt(1 + u^2) +
    # sin(mu) - cos(gamma_bar) <= 0, unless sin(mu) >= cos(gamma_bar) (b = inf: F > 0 on the whole tail, falling
    # towards sin(mu) from above).
    nodes = [a, *crit]
    if b < math.inf:
        nodes.append(max(b, 2.0 * nodes[-1]))
    vals = [F(x) for x in nodes]
    pieces: list[list[float]] = []
    for i in range(len(nodes) - 1):
        x0, x1, f0, f1 = nodes[i], nodes[i + 1], vals[i], vals[i + 1]
        if f0 < 0.0 and f1 < 0.0:
            continue
        lo = x0 if f0 >= 0.0 else root(F, x0, x1, g_lo)
        hi = x1 if f1 >= 0.0 else root(F, x1, x0, g_hi)
        if pieces and pieces[-1][1] == lo:
            pieces[-1][1] = hi
        else:
            pieces.append([lo, hi])
    if b == math.inf and vals[-1] >= 0.0:
        if pieces and pieces[-1][1] == nodes[-1]:
            pieces[-1][1] = math.inf
        else:
            pieces.append([nodes[-1], math.inf])
    if mu < 0.0:
        return [(-hi * t_z, -lo * t_z) for lo, hi in reversed(pieces)]
    return [(lo * t_z, hi * t_z) for lo, hi in pieces]


def _monotone_root(f, df, a: float, b: float, x: float) -> float:
    """Root of ``f``, monotone on [a, b] with a sign change there: Newton from ``x``, bisection when it leaves the
    bracket (an order of magnitude cheaper than scipy's brentq in this per-frame path)."""
    lo, hi = min(a, b), max(a, b)
    f_lo = f(lo)
    if not lo < x < hi:
        x = 0.5 * (lo + hi)
    for _ in range(100):
        fx = f(x)
        if fx == 0.0:
            return x
        if (fx < 0.0) == (f_lo < 0.0):
            lo = x
        else:
            hi = x
        d = df(x)
        xn = x - fx / d if d != 0.0 else 0.5 * (lo + hi)
        if not lo < xn < hi:
            xn = 0.5 * (lo + hi)
        if abs(xn - x) <= 1e-15 * (1.0 + abs(x)) or hi - lo <= 1e-15 * (1.0 + abs(lo)):
            return xn
        x = xn
    return x


def _tilt_room(t_y: float, t_z: float, u: tuple[float, float, float], p: GuidanceParams) -> float:
    """The largest tilt margin any ``t_x`` allowed by (a)-(c) reaches (-inf if none is); concave in s."""
    e = _envelope(t_y, t_z, u, p)
    if e is None:
        return -math.inf
    pieces, xm, b, K, u_x, c = e
    return max(_tilt_margin(max(lo, min(hi, xm)), b, K, u_x, c) for lo, hi in pieces)


def _best_tx(t_y: float, t_z: float, u: tuple[float, float, float], p: GuidanceParams) -> float | None:
    """Largest feasible ``t_x`` (thrust along the LOS) for fixed normal components, or None if none is."""
    e = _envelope(t_y, t_z, u, p)
    if e is None:
        return None
    pieces, xm_free, b, K, u_x, c = e
    if len(pieces) == 1:  # no uptilt: [-H, H] (twice a frame; the loop below gives the same)
        lo, hi = pieces[0]
        xm = xm_free if xm_free < hi else hi
        return _best_tx_in(lo, hi, xm if xm > lo else lo, b, K, u_x, c)  # max(lo, min(hi, xm_free))
    for lo, hi in reversed(pieces):  # the highest piece with a feasible point holds the largest t_x
        x = _best_tx_in(lo, hi, max(lo, min(hi, xm_free)), b, K, u_x, c)
        if x is not None:
            return x
    return None


def _best_tx_plain(t_y: float, t_z: float, u: tuple[float, float, float], p: GuidanceParams) -> float | None:
    """:func:`_best_tx` without uptilt (``abs(p.uptilt) <= _UPTILT_EPS``), the same floats: :func:`_envelope`'s one
    piece ``[-H, H]`` written out, without its lists and tuples, and the usual answer (``H`` within the tilt cone)
    before the maximiser of h is needed. :func:`solve` calls it twice a frame (tests/test_speed_identity.py)."""
    f_max = p.f_max
    if t_z < p.f_min - 1e-12 * f_max:  # (a)
        return None
    K = t_y * t_y + t_z * t_z
    r2 = f_max * f_max - K  # (b)
    if r2 < -1e-12 * f_max * f_max:
        return None
    r = math.sqrt(0.0 if r2 < 0.0 else r2)
    w = _fov_width(t_y, t_z, K, p)  # (c)
    if w is None:
        return None
    H = r if r < w else w  # min(w, r)
    u_x, u_y, u_z = u
    c = math.cos(p.max_tilt)
    b = u_y * t_y + u_z * t_z
    if u_x * H + b - c * math.sqrt(H * H + K) >= 0.0:  # _tilt_margin(H) >= 0: (d) holds at the top of the piece
        return H
    s2 = c * c - u_x * u_x
    xm = u_x * math.sqrt(K / s2) if s2 > 1e-15 else (math.copysign(math.inf, u_x) if u_x != 0.0 else 0.0)
    xm = xm if xm < H else H
    return _best_tx_in(-H, H, xm if xm > -H else -H, b, K, u_x, c)  # max(-H, min(H, xm))


def _best_tx_in(L: float, H: float, xm: float, b: float, K: float, u_x: float, c: float) -> float | None:
    """Largest ``t_x`` in ``[L, H]`` within the tilt cone (d); ``xm`` is h's maximiser clamped into ``[L, H]``."""
    if _tilt_margin(H, b, K, u_x, c) >= 0.0:
        return H
    tol = 1e-12 * (1.0 + math.sqrt(K) + abs(H))
    if _tilt_margin(xm, b, K, u_x, c) < -tol:
        return None
    # h(xm) >= 0 > h(H): the largest feasible t_x is the root of h in [xm, H]. Roots of the squared form
    # (u_x^2 - c^2) x^2 + 2 u_x b x + b^2 - c^2 K = 0 (one of them may belong to the mirrored cone).
    A, B, C = u_x * u_x - c * c, 2.0 * u_x * b, b * b - c * c * K
    cands: list[float] = []
    if abs(A) > 1e-14 * (1.0 + abs(B) + abs(C)):
        disc = B * B - 4.0 * A * C
        if disc >= 0.0:
            q = -0.5 * (B + math.copysign(math.sqrt(disc), B))
            cands = [q / A] + ([C / q] if q != 0.0 else [])
    elif B != 0.0:
        cands = [-C / B]
    best = None
    for x in cands:
        if xm - tol <= x <= H + tol and abs(_tilt_margin(x, b, K, u_x, c)) <= 1e-9 * (1.0 + math.sqrt(K)):
            best = x if best is None else max(best, x)
    if best is None:  # rounding defeated the closed form: bisect (h(lo) >= 0 > h(hi))
        lo, hi = xm, H
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if _tilt_margin(mid, b, K, u_x, c) >= 0.0 else (lo, mid)
        best = lo
    return max(xm, min(H, best))


def _max_scale_linear(c0: float, c1: float) -> float:
    """Largest s >= 0 with c0 + c1 s >= 0 (given c0 >= 0)."""
    return math.inf if c1 >= 0.0 else c0 / -c1


def demand_scale(a_y: float, a_z: float, g_y: float, g_z: float, p: GuidanceParams,
                 u: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> float | None:
    """Largest s in [0, 1] for which the demand ``s * (a_y, a_z)`` is feasible; None if s = 0 is not.

    ``u`` is world up in the PN frame (its tilt cone). Every constraint (a)-(d) of :func:`_best_tx` is convex
    in ``(t_x, s)``, so the feasible scales form an interval: closed-form bounds for (a), (b) and the paper's
    (c), then bisection when the tilt cone (d) is what binds.
    """
    return _demand_scale(a_y, a_z, g_y, g_z, p, u, {})


def _demand_scale(a_y: float, a_z: float, g_y: float, g_z: float, p: GuidanceParams,
                  u: tuple[float, float, float], memo: dict[float, float | None]) -> float | None:
    """:func:`demand_scale`, keeping every ``_best_tx`` it computes in ``memo`` (by scale) for :func:`solve`."""
    def feasible(s: float) -> bool:
        if s not in memo:
            memo[s] = _best_tx(s * a_y - g_y, s * a_z - g_z, u, p)
        return memo[s] is not None

    if not feasible(0.0):
        return None
    if feasible(1.0):
        return 1.0
    s = _max_scale_linear(max(-g_z - p.f_min, 0.0), a_z)  # (a) t_z >= f_min
    qa = a_y * a_y + a_z * a_z  # (b) |t_normal|^2 <= f_max^2  <=>  qa s^2 + qb s + qc <= 0
    qb = -2.0 * (a_y * g_y + a_z * g_z)
    qc = g_y * g_y + g_z * g_z - p.f_max * p.f_max
    if qa > _EPS:
        s = min(s, (-qb + math.sqrt(max(qb * qb - 4.0 * qa * qc, 0.0))) / (2.0 * qa))
    if p.fov == "paper":  # (c) necessary part: |t_y| <= t_z tan(gamma_bar)
        tg = math.tan(p.gamma_bar)
        s = min(s, _max_scale_linear(max(-g_z * tg + g_y, 0.0), a_z * tg - a_y),
                _max_scale_linear(max(-g_z * tg - g_y, 0.0), a_z * tg + a_y))
    s = max(0.0, min(1.0, s))
    if feasible(s):
        return s
    if abs(p.uptilt) > _UPTILT_EPS:  # the uptilted FOV bound (c) may bind too: bisect, keeping the feasible end
        lo, hi = 0.0, s
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if feasible(mid) else (lo, mid)
            if hi - lo <= 1e-13:
                break
        return lo
    # Only the tilt cone binds on [0, s]: the root of the concave tilt room r(s) (r(0) >= 0 > r(s)),
    # by regula falsi with the Illinois modification, keeping the feasible end.
    def room(x: float) -> float:
        return _tilt_room(x * a_y - g_y, x * a_z - g_z, u, p)

    lo, hi = 0.0, s
    r_lo, r_hi = room(lo), room(hi)
    side = 0
    for _ in range(60):
        if hi - lo <= 1e-13:
            break
        # -inf (no t_x at all: the (a)/(b) bound that gave s, reached with rounding): bisect toward lo.
        x = hi - r_hi * (hi - lo) / (r_hi - r_lo) if math.isfinite(r_hi) and r_hi != r_lo else 0.5 * (lo + hi)
        if not (lo < x < hi):
            x = 0.5 * (lo + hi)
        r = room(x)
        if r >= 0.0:
            lo, r_lo = x, r
            if side == -1:
                r_hi *= 0.5
            side = -1
        else:
            hi, r_hi = x, r
            if side == 1:
                r_lo *= 0.5
            side = 1
        if 0.0 <= r_lo <= 1e-12:
            break
    while not feasible(lo) and lo > 0.0:  # rounding at the boundary: step back inside
        lo = max(0.0, lo - 1e-12 - 1e-9 * lo)
    return lo


def _R_y_R_x(phi: float, theta: float) -> np.ndarray:
    """eq:meth_body_pn_rotation ``R_B^PN = R_y(phi) R_x(theta)``, multiplied out."""
    cp, sp, ct, st = math.cos(phi), math.sin(phi), math.cos(theta), math.sin(theta)
    return np.array((cp, sp * st, sp * ct, 0.0, ct, -st, -sp, cp * st, cp * ct)).reshape(3, 3)  # flat: cheaper


def solve(l: Vec3, a_n: Vec3, p: GuidanceParams, y_ref: np.ndarray | None = None) -> ThrustAttitude:  # noqa: E741
    """Closed-form optimum of eq:meth_optimization_problem_simplified with the flight envelope, and saturation.

    With ``t = s a_n^PN - g^PN`` normal to the LOS, the thrust along the LOS ``t_x = f sin(phi) cos(theta)`` is
    the objective; ``t_x*`` is the largest value the FOV bound, ``f_max`` and the tilt bound allow (without the
    tilt bound this is the paper's ``f_th* = min(f_max, (n_z a_n - g_z^PN) / cos(gamma_bar))`` for ``fov="paper"``
    and ``min(f_max, hypot(t_y, t_z / cos(gamma_bar)))`` for the exact bound). Then
    ``f_th* = |t|``, ``phi* = atan2(t_x, t_z)``, ``theta* = atan2(-t_y, hypot(t_x, t_z))``,
    ``R_B^W = R_PN^W R_y(phi*) R_x(theta*)``. ``l`` is the world-frame unit LOS (an array or three floats),
    ``a_n`` the PN demand (world; an array or three floats).
    """
    return ThrustAttitude(*solve_fields(l, a_n, p, y_ref))


# ThrustAttitude's fields in order: (f_th, phi, theta, R_W_B, demand_scale, fallback).
Solution = tuple[float, float, float, np.ndarray, float, bool]


def solve_fields(l: Vec3, a_n: Vec3, p: GuidanceParams, y_ref: np.ndarray | None = None) -> Solution:  # noqa: E741
    """:func:`solve`'s ThrustAttitude as the tuple of its fields (the controller's per-frame path: no object)."""
    rows = _pn_frame_rows(l, y_ref)
    ax, ay, az = a_n.tolist() if isinstance(a_n, np.ndarray) else a_n
    (_, yx, zx), (_, yy, zy), (lz, yz, zz) = rows
    a_y, a_z = yx * ax + yy * ay + yz * az, zx * ax + zy * ay + zz * az  # n_y a_n, n_z a_n
    g_y, g_z = -G * yz, -G * zz  # g^PN = R_W^PN g: its y part is 0 unless the LOS is vertical
    u = (lz, yz, zz)  # world up in the PN frame: the axis of the tilt cone
    # demand_scale's first two tests (s = 0, then s = 1) written out: most frames the full demand is feasible and
    # the search below is not needed (its closure and memo cost ~5 % of a controller step). The same _best_tx
    # calls with the same arguments, so the same s and t_x.
    best_tx = _best_tx_plain if abs(p.uptilt) <= _UPTILT_EPS else _best_tx  # the same t_x, the first cheaper
    if best_tx(0.0 * a_y - g_y, 0.0 * a_z - g_z, u, p) is None:
        return _fallback(_rows_array(rows), u, p)
    t_y, t_z = 1.0 * a_y - g_y, 1.0 * a_z - g_z  # s = 1
    t_x = best_tx(t_y, t_z, u, p)
    if t_x is not None:
        s = 1.0
    else:
        memo: dict[float, float | None] = {1.0: None}
        s = _demand_scale(a_y, a_z, g_y, g_z, p, u, memo)  # feasible(0) is computed again: rare
        if s is None:  # cannot happen: s = 0 was feasible above
            return _fallback(_rows_array(rows), u, p)
        t_x = memo[s] if s in memo else _best_tx(s * a_y - g_y, s * a_z - g_z, u, p)
        t_y, t_z = s * a_y - g_y, s * a_z - g_z
    if t_x is None:  # cannot happen: demand_scale checked this very s
        return _fallback(_rows_array(rows), u, p)
    f, theta, phi = angles_of_thrust(t_x, t_y, t_z)
    f = p.f_min if p.f_min > f else f  # min(f_max, max(f, f_min)): rounding only, (a) gives |t| >= t_z >= f_min
    f = f if f < p.f_max else p.f_max
    # R_W_PN.dot(_R_y_R_x(phi, theta)) with both factors in one array (one construction, not two, every frame),
    # an immutable one on the packed floats (cheaper than np.array's parsing of a tuple): the same two contiguous
    # 3x3 operands for BLAS, the same product (tests/test_speed_identity.py).
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = rows
    cp, sp, ct, st = math.cos(phi), math.sin(phi), math.cos(theta), math.sin(theta)
    M = np.ndarray((2, 3, 3), _F64, _PACK_2X3X3.pack(r00, r01, r02, r10, r11, r12, r20, r21, r22,
                                                      cp, sp * st, sp * ct, 0.0, ct, -st, -sp, cp * st, cp * ct))
    return f, phi, theta, M[0].dot(M[1]), s, False


def _rows_array(rows: list[list[float]]) -> np.ndarray:
    """A 3x3 array of a rotation's rows (floats)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = rows
    return np.array((r00, r01, r02, r10, r11, r12, r20, r21, r22)).reshape(3, 3)  # flat: cheaper than nested


def _fallback(R_W_PN: np.ndarray, u: tuple[float, float, float], p: GuidanceParams) -> Solution:
    """No demand is feasible (LOS steeper than the FOV and tilt bounds together allow, or too steep for f_min).

    Wings level about the LOS (theta = 0) and the optical axis as close to the LOS as the tilt bound allows:
    the thrust axis ``(sin phi, 0, cos phi)`` makes the angle ``|phi - alpha|`` with up, ``alpha = atan2(u_x, u_z)``,
    so ``phi = clip(uptilt, alpha - max_tilt, alpha + max_tilt)`` (the optical axis is ``|phi - uptilt|`` off the
    LOS). Thrust holds altitude, within the thrust limits.
    """
    alpha = math.atan2(u[0], u[2])
    phi = max(alpha - p.max_tilt, min(alpha + p.max_tilt, p.uptilt))  # optical axis at phi - uptilt from the LOS
    up = u[0] * math.sin(phi) + u[2] * math.cos(phi)  # cos(tilt) > 0
    f = min(p.f_max, max(p.f_min, G / up if up > _EPS else p.f_min))
    return f, phi, 0.0, R_W_PN.dot(_R_y_R_x(phi, 0.0)), 0.0, True


@fast_init
@dataclass(frozen=True, slots=True)
class Setpoint:
    """What goes to MAVSDK ``Offboard.set_attitude``: NED/FRD Euler (deg, absolute yaw) + thrust 0..1."""

    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    thrust: float
    R_ned_frd: np.ndarray  # the same attitude as a rotation matrix (body FRD -> world NED)

    def q_wxyz(self) -> np.ndarray:
        """The attitude as a scalar-first quaternion (MAVLink SET_ATTITUDE_TARGET order)."""
        return quat_wxyz_from_R(self.R_ned_frd)


def normalised_thrust(f_th: float, hover_thrust: float, thrust_min: float) -> float:
    """PX4's collective thrust 0..1 from mass-normalised thrust: ``hover_thrust * f_th / g``, clamped.

    Never 0: a quadrotor at zero thrust falls and cannot recover.
    """
    u = hover_thrust * f_th / G
    u = u if u > thrust_min else thrust_min  # min(1.0, max(thrust_min, u))
    return u if u < 1.0 else 1.0


def to_setpoint(R_W_B: np.ndarray, f_th: float, hover_thrust: float, thrust_min: float) -> Setpoint:
    """The one conversion from the paper's frames (ENU/FLU) to a MAVSDK setpoint (NED/FRD)."""
    # = P_NED_ENU @ R_W_B @ F_FRD_FLU = R_W_B[_ENU_TO_NED_ROWS] * _NED_FRD_SIGNS, without two matmuls; in floats
    # (x * 1.0 is x and x * -1.0 is -x, exactly as numpy's elementwise product, signed zeros included).
    (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = R_W_B.tolist()
    a1, a2, b1, b2, c0 = -a1, -a2, -b1, -b2, -c0  # negated once: the rows are (b0, b1, b2), (a0, a1, a2), (c0, c1, c2)
    roll, pitch, yaw = euler_ned_deg_of(b0, b1, a0, a1, c0, c1, c2)
    R = np.array((b0, b1, b2, a0, a1, a2, c0, c1, c2)).reshape(3, 3)  # the rows, flat: cheaper than nested
    return Setpoint(roll, pitch, yaw, normalised_thrust(f_th, hover_thrust, thrust_min), R)


def hover_setpoint(yaw_deg: float, hover_thrust: float) -> Setpoint:
    """Level attitude at the given yaw with hover thrust: the recover / no-target command."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return Setpoint(0.0, 0.0, yaw_deg, hover_thrust, R)


def straight_pass(l: np.ndarray, f_min: float, f_max: float, y_ref: np.ndarray | None = None,  # noqa: E741
                  max_tilt: float = math.pi / 2, drag: np.ndarray | None = None) -> ThrustAttitude:
    """The gate pass: zero PN demand, no bank held from the PN law, the optical axis on (or nearest to) the LOS
    ``l`` (world, unit).

    Without ``drag``: optical axis on the LOS, no roll about it (body y horizontal: the PN frame with
    phi = theta = 0) and the thrust whose vertical part carries the weight, ``f = g / (e_z . z_B)`` within
    [f_min, f_max]. The net acceleration is then horizontal and along the LOS's heading (``-g tan(elevation)``):
    no climb, no sink. The tilt equals the LOS elevation; a LOS steeper than ``max_tilt`` (rad) gets the axis
    of the same heading at elevation +-max_tilt (the envelope wins over pointing).

    With ``drag`` (the aerodynamic acceleration the accelerometer measures, world, m/s^2): the thrust cancels
    gravity and drag, ``t = g e_z - drag``, so the vehicle keeps its velocity (flies straight) through the
    gate. The straight line PN has aimed at the gate is flown: on a draggy vehicle chasing a moving gate,
    levelling the thrust instead loses the lateral speed in the last half second (~1 m of miss on the SIH
    profile, docs/guidance.md "Evening session"). Body x is the LOS projected normal to the thrust axis.
    Tilt at most ``max_tilt`` (the horizontal part is shortened), ``|t|`` within [f_min, f_max].
    """
    lx, ly, lz = (float(v) for v in l)
    if drag is not None:
        dx, dy, dz = (float(v) for v in drag)
        if all(math.isfinite(v) for v in (dx, dy, dz)):
            return _drag_pass(np.array([lx, ly, lz]), np.array([-dx, -dy, G - dz]), f_min, f_max, max_tilt, y_ref)
    h = math.hypot(lx, ly)
    elev = math.atan2(lz, h)
    if abs(elev) > max_tilt and h > 1e-9:
        e = math.copysign(max_tilt, elev)
        l = np.array([lx / h * math.cos(e), ly / h * math.cos(e), math.sin(e)])  # noqa: E741
    R_W_PN = pn_frame(l, y_ref)
    up = float(R_W_PN[2, 2])  # vertical part of the thrust axis: cos(LOS elevation)
    f = min(f_max, max(f_min, G / max(up, 1e-3)))
    return ThrustAttitude(f, 0.0, 0.0, R_W_PN, 0.0, False)


def _drag_pass(l: np.ndarray, t: np.ndarray, f_min: float, f_max: float, max_tilt: float,  # noqa: E741
               y_ref: np.ndarray | None) -> ThrustAttitude:
    """straight_pass with a thrust vector ``t`` (world): envelope, then the attitude nearest the LOS."""
    tz = max(float(t[2]), _EPS)  # the thrust always carries the weight: never pointed down
    th = math.hypot(float(t[0]), float(t[1]))
    k = min(1.0, tz * math.tan(max_tilt) / th) if th > _EPS else 1.0
    t = np.array([t[0] * k, t[1] * k, tz])
    n = math.sqrt(t.dot(t))
    f = min(f_max, max(f_min, n))
    z = t / n
    x = l - float(l.dot(z)) * z
    nx = math.sqrt(x.dot(x))
    if nx < 1e-6:  # LOS along the thrust axis (not a pass geometry): any body x normal to z
        x = pn_frame(z, y_ref)[:, 1]
        nx = math.sqrt(x.dot(x))
    x = x / nx
    R = np.column_stack((x, np.cross(z, x), z))
    return ThrustAttitude(f, 0.0, 0.0, R, 0.0, False)


def ring_view_gamma(gamma_bar: float, half_fov: float, ring_angle: float, margin: float,
                    gamma_min: float) -> float:
    """The FOV bound that keeps the whole ring in the image, not only its centre (rad in, rad out).

    The paper's bound keeps the LOS (the gate centre) within ``gamma_bar`` of the optical axis. A detector
    boxes the ring, and a ring cut by the image border gives a box whose centre is pulled towards the image
    centre (a vertical and, when the vehicle banks, a lateral LOS error of tens of pixels in the last metres).
    The LOS sits ``phi`` from the optical axis and the rim up to ``ring_angle`` (its angular radius) beyond it:
    the rim stays inside a view of half angle ``half_fov`` while ``phi <= half_fov - ring_angle - margin``.
    Never above ``gamma_bar``; never below ``gamma_min`` (a ring larger than the view is cut whatever we do:
    then some thrust along the LOS stays allowed)."""
    g = half_fov - max(ring_angle, 0.0) - margin
    return min(gamma_bar, max(gamma_min, g))
