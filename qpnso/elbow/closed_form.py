"""The closed forms of S-R-S arms as Numba kernels: self-motion rows and the continuity interval
(docs/method.md §4–5, [E 7]–[E 9]).

One implementation for the library and the control tick: :mod:`qpnso.elbow.srs` (``SelfMotion``, ``ik``)
and :mod:`qpnso.elbow.intervals` (``continuity_interval``, ``feasible_intervals``) call these kernels from
Python; the tick renews its continuity interval with :func:`srs_interval` inside its own kernel
(:func:`qpnso.control.memory.renew_interval`), at the cost of an ordinary tick.

The arm's geometry is a record (:func:`srs_dtype`, filled by :func:`qpnso.elbow.srs.srs_geometry`).  For a
tool pose ``(R, p)`` and a branch (signs of joints 2, 4, 6), :func:`self_motion_rows` writes every joint as a
function of the arm angle ``ns``: row k of ``num``/``den`` holds ``(a, b, c)`` of ``a·sin ns + b·cos ns + c``;
joints 1, 3, 5, 7 are ``sign·atan2(num, den)``, joints 2, 6 ``sign·acos(den)``, joint 4 a constant.

Every limit crossing solves ``a sin ns + b cos ns = c`` exactly (:func:`crossings`); joints 2 and 6 through 0
are singular cuts (:func:`singular_cut`).  :func:`closed_form_interval` is [E 9]: the nearest genuine exit
on each side of the current arm angle.  An end is named by a code (:data:`NO_END`, a limit ``2·joint +
is_max``, a singular cut ``−1 − joint``; joints 0-based).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from qpnso.linalg import matmul

TWO_PI = 2.0 * math.pi
SINGULAR_TOL = 1e-12
"""A cosine-type joint whose ``cos θ`` reaches 1 − SINGULAR_TOL passes through 0 (singular cut)."""
CUT_TIE = 1e-9
"""rad: a singular cut this close to the nearest limit crossing (or nearer) ends the interval and names it."""
END_AT_START = 1e-9
"""rad: an exit crossing this close to the current arm angle is at it (distance 0)."""

TAN, COS, CONST = 0, 1, 2
KIND = np.array([TAN, COS, TAN, CONST, TAN, COS, TAN])
"""Type of each joint's closed form: tangent (atan2), cosine (acos) or constant (joint 4)."""

SRS_OK, SRS_UNREACHABLE, SRS_WRIST_VERTICAL, SRS_ELBOW_STRAIGHT = 0, 1, 2, 3
"""Codes of :func:`self_motion_rows` and :func:`srs_interval`: done; the shoulder–wrist distance is out of
reach; the wrist centre is on the vertical through the shoulder (arm angle undefined); the elbow is straight."""

NO_END = -100
"""End code of a side that no limit or singular cut closes."""
ROW_FIELDS = 7
"""Columns of a limit row (:func:`limit_rows`): joint, tangent (0/1), cos φ, sin φ, cos θ_limit, rate sign, is_max."""
MAX_ROWS = 12


def srs_dtype() -> np.dtype:
    """The S-R-S geometry record (:class:`qpnso.elbow.srs.SrsGeometry` for the kernels): ``shoulder_from_world``
    (3×4, world points to the shoulder frame), ``tool_to_wrist`` (4×4, the wrist frame in the tool frame), the
    upper-arm and forearm lengths (m), the world ``vertical`` in the shoulder frame, each joint's ``axis_sign``."""
    f8 = np.float64
    return np.dtype(
        [
            ("shoulder_from_world", f8, (3, 4)),
            ("tool_to_wrist", f8, (4, 4)),
            ("upper_arm_m", f8),
            ("forearm_m", f8),
            ("vertical", f8, 3),
            ("axis_sign", f8, 7),
        ]
    )


@njit(cache=True)
def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(cache=True)
def _r03_transposed(p, q, r, sin_a, cos_a, k_x, k_y, out, at):
    """``R03ᵀ·v`` for ``v = (p, q, r)`` given in the arm-angle frame ``(u_sin, u_cos, u)``, each component as its
    ``(sin ns, cos ns, 1)`` coefficients, into rows ``at``, ``at+1``, ``at+2`` of ``out``:
    ``R03·ez = e1 = sin_a·(sin ns·u_sin + cos ns·u_cos) + cos_a·u`` (upper arm),
    ``R03·ex = k_x·e1 + k_y·u`` (= (e2 − e1 cos q4)/(σ4 sin q4), e2 = (d·u − l1·e1)/l2),
    ``R03·ey = e1 × R03·ex = k_y·(e1 × u)``."""
    e0, e1, e2 = sin_a * p, sin_a * q, cos_a * r
    out[at, 0], out[at, 1], out[at, 2] = k_x * e0, k_x * e1, k_x * e2 + k_y * r
    out[at + 1, 0], out[at + 1, 1], out[at + 1, 2] = -k_y * e1, k_y * e0, 0.0
    out[at + 2, 0], out[at + 2, 1], out[at + 2, 2] = e0, e1, e2


@njit(cache=True)
def self_motion_rows(G, R, p, s2, s4, s6, num, den, sign):
    """The closed-form self-motion (Shimizu et al., IEEE T-RO 2008) of the geometry record ``G`` for the tool
    pose ``R`` (world ← tool), ``p`` (m, world) and the branch signs ``s2, s4, s6`` (±1): ``num``, ``den`` (7×3)
    and ``sign`` (7,) written (module docstring).  ``R03`` (joints 1–3) and ``R47 = R4ᵀ·R03ᵀ·T`` (joints 5–7, T
    the wrist's rotation) are affine in ``(sin ns, cos ns, 1)``; their last columns and rows give the Z-Y-Z
    angles ``qa = σa·atan2(sb·M12, sb·M02)``, ``qb = s·acos(M22)``, ``qc = σc·atan2(sb·M21, −sb·M20)``.
    Returns ``(code, q4, dist)``: :data:`SRS_OK` or why not, joint 4 (rad), the shoulder–wrist distance (m)."""
    axis, l1, l2 = G.axis_sign, G.upper_arm_m, G.forearm_m
    H = np.zeros((4, 4))  # the tool pose, homogeneous
    H[:3, :3], H[:3, 3], H[3, 3] = R, p, 1.0
    a = matmul(matmul(G.shoulder_from_world, H), G.tool_to_wrist)  # [T | p_sw] in the shoulder frame
    dist = math.sqrt(a[0, 3] ** 2 + a[1, 3] ** 2 + a[2, 3] ** 2)
    if dist > l1 + l2 or dist < abs(l1 - l2):
        return SRS_UNREACHABLE, 0.0, dist
    cos4 = (dist * dist - l1 * l1 - l2 * l2) / (2 * l1 * l2)
    sin4 = s4 * math.sqrt(max(0.0, 1.0 - cos4 * cos4))
    u = (a[0, 3] / dist, a[1, 3] / dist, a[2, 3] / dist)
    v = G.vertical
    zx = _cross(v[0], v[1], v[2], u[0], u[1], u[2])
    n_zx = math.sqrt(zx[0] ** 2 + zx[1] ** 2 + zx[2] ** 2)
    if n_zx < 1e-12:
        return SRS_WRIST_VERTICAL, 0.0, dist
    if abs(sin4) < 1e-12:
        return SRS_ELBOW_STRAIGHT, 0.0, dist
    u_sin = (zx[0] / n_zx, zx[1] / n_zx, zx[2] / n_zx)
    u_cos = _cross(u[0], u[1], u[2], u_sin[0], u_sin[1], u_sin[2])
    cos_a = (l1 * l1 + dist * dist - l2 * l2) / (2 * l1 * dist)
    sin_a = math.sqrt(max(0.0, 1.0 - cos_a * cos_a))
    c4 = max(-1.0, min(1.0, cos4))
    s4a = axis[3] * sin4  # R4 = Ry(σ4·q4): cosine c4, sine s4a
    k_x, k_y = (-(l1 / l2) - cos4) / s4a, (dist / l2) / s4a
    # blocks of 3 rows, each (sin, cos, 1): col03 (R03·ez), row03 (R03ᵀ·ez), R03ᵀ·t2 as x, y, e; col47, row47
    c = np.empty((15, 3))
    for i in range(3):
        c[i, 0], c[i, 1], c[i, 2] = sin_a * u_sin[i], sin_a * u_cos[i], cos_a * u[i]
    _r03_transposed(u_sin[2], u_cos[2], u[2], sin_a, cos_a, k_x, k_y, c, 3)
    tb = np.empty((3, 3))  # T's columns in the arm-angle frame
    for i in range(3):
        for j, b in enumerate((u_sin, u_cos, u)):
            tb[i, j] = a[0, i] * b[0] + a[1, i] * b[1] + a[2, i] * b[2]
    _r03_transposed(tb[2, 0], tb[2, 1], tb[2, 2], sin_a, cos_a, k_x, k_y, c, 6)
    kappa, k_u = s4a * k_x + c4, s4a * k_y  # R03·R4·ez = κ·e1 + s4·k_y·u
    for j in range(3):
        x, y, e = c[6, j], c[7, j], c[8, j]
        c[9, j], c[10, j], c[11, j] = c4 * x - s4a * e, y, s4a * x + c4 * e  # R4ᵀ·R03ᵀ·t2
        c[12 + j, 0], c[12 + j, 1] = kappa * sin_a * tb[j, 0], kappa * sin_a * tb[j, 1]
        c[12 + j, 2] = (kappa * cos_a + k_u) * tb[j, 2]
    sb03, sb47 = s2 * axis[1], s6 * axis[5]
    for j in range(3):
        num[0, j], num[1, j], num[2, j] = sb03 * c[1, j], 0.0, sb03 * c[4, j]
        den[0, j], den[1, j], den[2, j] = sb03 * c[0, j], c[2, j], -sb03 * c[3, j]
        num[3, j], den[3, j] = 0.0, 0.0
        num[4, j], num[5, j], num[6, j] = sb47 * c[10, j], 0.0, sb47 * c[13, j]
        den[4, j], den[5, j], den[6, j] = sb47 * c[9, j], c[11, j], -sb47 * c[12, j]
    for k in range(7):
        middle = s2 if k < 3 else (s4 if k == 3 else s6)
        sign[k] = middle if KIND[k] == COS else axis[k]
    return SRS_OK, s4 * math.acos(c4), dist


@njit(cache=True)
def limit_rows(sign, q_min, q_max, rows):
    """The joint limits that can bind for the joint signs ``sign`` (joint-major, min before max) into ``rows``
    (:data:`MAX_ROWS` × :data:`ROW_FIELDS`): the joint, 1 for a tangent-type joint, ``cos φ``, ``sin φ`` of
    φ = sign·θ_limit, ``cos θ_limit``, the rate sign (dθ/dns has the sign of ``rate·d(residual)/dns`` at a
    genuine root) and 1 for the upper bound.  A cosine-type joint ``θ = s·acos(x)`` never reaches a bound of
    the other sign.  Returns the number of rows."""
    n = 0
    for k in range(7):
        if KIND[k] == CONST:
            continue
        s, tangent = sign[k], KIND[k] == TAN
        for bound in range(2):
            theta = q_max[k] if bound else q_min[k]
            if tangent or theta * s >= 0:
                phi = s * theta
                rows[n, 0], rows[n, 1] = k, 1.0 if tangent else 0.0
                rows[n, 2], rows[n, 3], rows[n, 4] = math.cos(phi), math.sin(phi), math.cos(theta)
                rows[n, 5], rows[n, 6] = s if tangent else -s, bound
                n += 1
    return n


@njit(cache=True)
def crossings(row, num_k, den_k, genuine_only, out):
    """Arm angles where a limit ``row`` (:func:`limit_rows`) is crossed [E 7], with the residual's slope there,
    into ``out`` (2×2: ``x``, slope); returns how many.

    The crossings solve ``a sin ns + b cos ns = c`` exactly — tangent type: ``atan2(num, den) = φ`` ⇔
    ``num cos φ − den sin φ = 0``; cosine type: ``den = cos θ_limit`` — at ``atan2(a, b) ± δ``, ``δ = acos(c/r)``
    (``r = √(a²+b²)``; ``|c| ≤ r`` keeps ``c/r`` in [-1, 1] exactly), each polished by one Newton step; the
    slope there is ``∓ r sin δ``.  A tangent-type root is genuine where ``(num, den)`` points along φ, not
    φ + π (``num sin φ + den cos φ > 0``); ``genuine_only`` drops the others."""
    tangent, cp, sp = row[1] != 0.0, row[2], row[3]
    if tangent:
        a, b = num_k[0] * cp - den_k[0] * sp, num_k[1] * cp - den_k[1] * sp
        c = den_k[2] * sp - num_k[2] * cp
    else:
        a, b, c = den_k[0], den_k[1], row[4] - den_k[2]
    r = math.hypot(a, b)
    if not (r > 1e-14 and abs(c) <= r):
        return 0
    delta = math.acos(c / r)
    base, slope = math.atan2(a, b), r * math.sin(delta)
    count = 0
    for side in range(2):
        x, rate = (base + delta, -slope) if side == 0 else (base - delta, slope)
        sx, cx = math.sin(x), math.cos(x)
        if genuine_only and tangent:
            along = (num_k[0] * sx + num_k[1] * cx + num_k[2]) * sp + (den_k[0] * sx + den_k[1] * cx + den_k[2]) * cp
            if not along > 0:
                continue
        df = a * cx - b * sx
        out[count, 0] = x - (a * sx + b * cx - c) / df if abs(df) > 1e-6 * r else x
        out[count, 1] = rate
        count += 1
    return count


@njit(cache=True)
def singular_cut(den, k):
    """``(True, ns)`` where joint ``k`` (1 or 5, 0-based: joints 2 and 6) passes through 0 (``cos θ_k`` reaches
    1 within :data:`SINGULAR_TOL`), else ``(False, 0)``."""
    sa, cb, c0 = den[k, 0], den[k, 1], den[k, 2]
    if c0 + math.hypot(sa, cb) >= 1.0 - SINGULAR_TOL:
        return True, math.atan2(sa, cb)
    return False, 0.0


@njit(cache=True)
def _nearer(best, candidate):
    """The nearer of two ends ``(distance, tie-break order, code)``."""
    if candidate[0] < best[0] or (candidate[0] == best[0] and candidate[1] < best[1]):
        return candidate
    return best


@njit(cache=True)
def _cut_or_crossing(crossing, cut):
    """The end of one side: the singular ``cut`` unless a limit crossing is nearer by more than :data:`CUT_TIE`.
    At a cut, joints 1 and 3 (5 and 7) jump by π, and their closed form shows a "crossing" at the cut itself:
    without the tie, it named a limit of joint 3 that the joint was 80° away from."""
    return cut if cut[0] <= crossing[0] + CUT_TIE else crossing


@njit(cache=True)
def closed_form_interval(num, den, sign, ns0, q_min, q_max):
    """[E 9] directly: the nearest genuine exit crossing (or singular cut) on each side of ``ns0`` (rad).

    Valid because the configuration at ``ns0`` is within all limits: moving away from it, the first limit
    crossing of any joint is where that joint leaves; the residual's slope at a genuine root gives the
    direction in which it leaves its bound.  Returns ``(below, above, lo_code, hi_code)``: the distances (rad)
    from ``ns0`` to the ends (``inf`` where none) and their codes."""
    rows = np.empty((MAX_ROWS, ROW_FIELDS))
    n = limit_rows(sign, q_min, q_max, rows)
    roots = np.empty((2, 2))
    hi = (math.inf, 0, NO_END)  # (distance, tie-break order, code)
    lo = hi
    for i in range(n):
        k, rate_sign, is_max = int(rows[i, 0]), rows[i, 5], rows[i, 6] != 0.0
        code = 2 * k + int(is_max)
        for j in range(crossings(rows[i], num[k], den[k], True, roots)):
            ahead = (roots[j, 0] - ns0) % TWO_PI  # behind = 2π − ahead
            if (roots[j, 1] * rate_sign > 0) == is_max:
                hi = _nearer(hi, (0.0 if ahead > TWO_PI - END_AT_START else ahead, i + j * n, code))
            else:
                lo = _nearer(lo, (0.0 if ahead < END_AT_START else TWO_PI - ahead, i + j * n, code))
    for k in (1, 5):  # joints 2 and 6 through 0: singular cuts end the interval on both sides
        hit, x = singular_cut(den, k)
        if hit:
            hi = _cut_or_crossing(hi, ((x - ns0) % TWO_PI, 2 * n + k, -1 - k))
            lo = _cut_or_crossing(lo, ((ns0 - x) % TWO_PI, 2 * n + k, -1 - k))
    return lo[0], hi[0], lo[2], hi[2]


@njit(cache=True)
def srs_interval(G, R, p, s2, s4, s6, ns, q_min, q_max):
    """The continuity interval [E 9] at the tool pose ``R``, ``p`` (m) on the branch ``s2, s4, s6``, holding the
    arm angle ``ns`` (rad, any unwrapping) of a configuration within ``[q_min, q_max]``.  Returns
    ``(code, lo, hi, full_circle, lo_code, hi_code, dist)``: :data:`SRS_OK` or why not
    (:func:`self_motion_rows`), the ends (rad; the full circle ``ns ± π`` when nothing binds), their codes, the
    shoulder–wrist distance (m)."""
    num, den, sign = np.empty((7, 3)), np.empty((7, 3)), np.empty(7)
    code, _, dist = self_motion_rows(G, R, p, s2, s4, s6, num, den, sign)
    if code != SRS_OK:
        return code, ns, ns, False, NO_END, NO_END, dist
    below, above, lo_code, hi_code = closed_form_interval(num, den, sign, ns, q_min, q_max)
    if math.isinf(below) and math.isinf(above):
        return SRS_OK, ns - math.pi, ns + math.pi, True, NO_END, NO_END, dist
    return SRS_OK, ns - below, ns + above, False, lo_code, hi_code, dist


@njit(cache=True)
def joints_at(num, den, sign, q4, ns, out):
    """The joints (rad) at the arm angle ``ns`` (rad) of the self-motion rows of :func:`self_motion_rows` into
    ``out`` (7,) (module docstring): with ``x = (sin ns, cos ns, 1)``, tangent type ``sign·atan2(num·x, den·x)``,
    cosine type ``sign·acos(den·x)`` (``den·x`` clipped to [−1, 1]), joint 4 the constant ``q4``."""
    s, c = math.sin(ns), math.cos(ns)
    for k in range(7):
        d = den[k, 0] * s + den[k, 1] * c + den[k, 2]
        if KIND[k] == TAN:
            out[k] = sign[k] * math.atan2(num[k, 0] * s + num[k, 1] * c + num[k, 2], d)
        elif KIND[k] == COS:
            out[k] = sign[k] * math.acos(min(1.0, max(-1.0, d)))
        else:
            out[k] = q4


@njit(cache=True)
def joints_along(num, den, sign, q4, ns, out):
    """:func:`joints_at` for every arm angle of ``ns`` (N,) into the rows of ``out`` (N, 7)."""
    for i in range(ns.shape[0]):
        joints_at(num, den, sign, q4, ns[i], out[i])


@njit(cache=True)
def srs_ik(G, R, p, s2, s4, s6, ns, out):
    """Closed-form IK of the S-R-S arm ``G`` (docs/method.md §4): the joints (rad) at the tool pose ``R``
    (world ← tool), ``p`` (m, world), on the branch ``s2, s4, s6`` (±1), at the arm angle ``ns`` (rad) into
    ``out`` (7,) (:func:`self_motion_rows`, then :func:`joints_at`; joint limits not checked).  Returns ``(code,
    dist)`` of :func:`self_motion_rows`; ``out`` is written only when the code is :data:`SRS_OK`."""
    num, den, sign = np.empty((7, 3)), np.empty((7, 3)), np.empty(7)
    code, q4, dist = self_motion_rows(G, R, p, s2, s4, s6, num, den, sign)
    if code == SRS_OK:
        joints_at(num, den, sign, q4, ns, out)
    return code, dist


@njit(cache=True)
def branch_signs(q):
    """The branch of ``q`` (rad): signs (±1.0) of joints 2, 4, 6, and False if one of them is exactly 0."""
    s2, s4, s6 = (1.0 if q[1] > 0 else -1.0), (1.0 if q[3] > 0 else -1.0), (1.0 if q[5] > 0 else -1.0)
    return s2, s4, s6, q[1] != 0.0 and q[3] != 0.0 and q[5] != 0.0
