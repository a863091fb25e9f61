"""Distances from a link capsule's axis to obstacle primitives, as Numba kernels for the control tick.

A link is a capsule: a line segment ``a``–``b`` (its axis) swept by the link radius.  These kernels give the
distance from the SEGMENT to an obstacle primitive, the witness parameter ``t ∈ [0, 1]`` (the segment's
closest point is ``a + t (b − a)``) and the unit normal ``n`` pointing FROM the obstacle TOWARD that closest
point, so that ``∂dist/∂x = n`` for the segment point ``x`` (envelope theorem: moving the whole segment by
``δ`` changes the distance by ``n·δ``, moving ``a`` alone by ``(1 − t) n·δ``, ``b`` alone by ``t n·δ``).
The caller subtracts the link radius.

Units and frames: every point, vector and length is in the world frame, in metres; a box's orientation is
``R`` (3×3, world ← box: its columns are the box axes) and its half extents ``half`` (3,).  Each kernel
returns the tuple ``(dist, t, n0, n1, n2)``.

All are closed forms, no iteration (one implementation for the library and the tick):

* :func:`segment_point` — segment–point (projection clamped to the segment);
* :func:`segment_segment` — segment–segment, the clamped closed form of Ericson, *Real-Time Collision
  Detection* §5.1.9 (parallel and degenerate segments included);
* :func:`segment_box` — segment–oriented box, exact minimisation of the convex piecewise-quadratic squared
  distance over its pieces; a segment that enters the box gets a NEGATIVE distance (minus its depth);
* :func:`segment_obstacle` — the dispatcher on the obstacle kind (:data:`SPHERE`, :data:`CAPSULE`,
  :data:`BOX`), distance to the obstacle's surface.

Where the distance is 0 (the point on the segment, crossing segments) the normal is some unit vector
perpendicular to the segment, never NaN; outputs are finite for finite inputs.  tests/test_distance.py
checks the kernels against coal (``coal.distance``) and against brute force over a fine grid of ``t``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SPHERE = 0
"""Obstacle kind: a sphere (``center``, ``radius``)."""
CAPSULE = 1
"""Obstacle kind: a capsule (axis ``center``–``second``, ``radius``)."""
BOX = 2
"""Obstacle kind: an oriented box (``center``, ``R`` world ← box, half extents ``half``)."""


@njit(cache=True)
def _clamp01(x):
    """``x`` clamped to [0, 1] (NaN-free for ±inf)."""
    if x < 0.0:
        return 0.0
    if x > 1.0:
        return 1.0
    return x


@njit(cache=True)
def _normalize(v0, v1, v2):
    """``(u0, u1, u2, |v|)``: the unit vector along ``v`` and its norm, scaled against over- and underflow;
    ``(0, 0, 0, 0)`` for ``v = 0``."""
    m = max(abs(v0), abs(v1), abs(v2))
    if not m > 0.0:
        return 0.0, 0.0, 0.0, 0.0
    w0, w1, w2 = v0 / m, v1 / m, v2 / m
    s = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    return w0 / s, w1 / s, w2 / s, m * s


@njit(cache=True)
def _perpendicular(d0, d1, d2):
    """A unit vector perpendicular to ``d`` (``d × e_k`` for the axis ``e_k`` least along ``d``); ``e_x``
    for ``d = 0``."""
    ax, ay, az = abs(d0), abs(d1), abs(d2)
    if ax <= ay and ax <= az:
        c0, c1, c2 = 0.0, d2, -d1
    elif ay <= az:
        c0, c1, c2 = -d2, 0.0, d0
    else:
        c0, c1, c2 = d1, -d0, 0.0
    u0, u1, u2, s = _normalize(c0, c1, c2)
    if s > 0.0:
        return u0, u1, u2
    return 1.0, 0.0, 0.0


@njit(cache=True)
def segment_point(a, b, p):
    """Distance from the segment ``a``–``b`` to the point ``p`` (m): ``(dist, t, n0, n1, n2)``.

    Closed form: the projection ``t = (p − a)·(b − a) / |b − a|²`` clamped to [0, 1] (``t = 0`` for a
    degenerate segment ``a = b``); ``n = (x(t) − p)/dist``.  For a sphere obstacle the caller subtracts its
    radius.  If ``p`` is on the segment (dist 0), ``n`` is a unit vector perpendicular to the segment."""
    d0, d1, d2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    dd = d0 * d0 + d1 * d1 + d2 * d2
    t = 0.0
    if dd > 0.0:
        t = _clamp01(((p[0] - a[0]) * d0 + (p[1] - a[1]) * d1 + (p[2] - a[2]) * d2) / dd)
    if t == 1.0:
        x0, x1, x2 = b[0], b[1], b[2]
    else:
        x0, x1, x2 = a[0] + t * d0, a[1] + t * d1, a[2] + t * d2
    n0, n1, n2, dist = _normalize(x0 - p[0], x1 - p[1], x2 - p[2])
    if not dist > 0.0:
        n0, n1, n2 = _perpendicular(d0, d1, d2)
        dist = 0.0
    return dist, t, n0, n1, n2


@njit(cache=True)
def segment_segment(a, b, c, e):
    """Distance between the segments ``a``–``b`` and ``c``–``e`` (m): ``(dist, t, n0, n1, n2)``, ``t`` on
    ``a``–``b``, ``n`` from the closest point of ``c``–``e`` toward that of ``a``–``b``.

    Closed form: Ericson, *Real-Time Collision Detection* §5.1.9 — the closest points of the two lines,
    ``t`` clamped to [0, 1], the parameter on ``c``–``e`` recomputed for it and, if that one leaves [0, 1],
    clamped and ``t`` recomputed.  Parallel segments (zero determinant) start from ``t = 0``; a degenerate
    segment is a point.  Crossing segments (dist 0) get ``n`` along ``(b − a) × (e − c)``, or else a unit
    vector perpendicular to a segment."""
    d10, d11, d12 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    d20, d21, d22 = e[0] - c[0], e[1] - c[1], e[2] - c[2]
    r0, r1, r2 = a[0] - c[0], a[1] - c[1], a[2] - c[2]
    aa = d10 * d10 + d11 * d11 + d12 * d12
    ee = d20 * d20 + d21 * d21 + d22 * d22
    f = d20 * r0 + d21 * r1 + d22 * r2
    s = 0.0  # on a–b
    u = 0.0  # on c–e
    if aa <= 0.0 and ee <= 0.0:
        pass
    elif aa <= 0.0:
        u = _clamp01(f / ee)
    else:
        cc = d10 * r0 + d11 * r1 + d12 * r2
        if ee <= 0.0:
            s = _clamp01(-cc / aa)
        else:
            bb = d10 * d20 + d11 * d21 + d12 * d22
            denom = aa * ee - bb * bb
            if denom > 0.0:
                s = _clamp01((bb * f - cc * ee) / denom)
            u = (bb * s + f) / ee
            if u < 0.0:
                u = 0.0
                s = _clamp01(-cc / aa)
            elif u > 1.0:
                u = 1.0
                s = _clamp01((bb - cc) / aa)
    if s == 1.0:
        x0, x1, x2 = b[0], b[1], b[2]
    else:
        x0, x1, x2 = a[0] + s * d10, a[1] + s * d11, a[2] + s * d12
    if u == 1.0:
        y0, y1, y2 = e[0], e[1], e[2]
    else:
        y0, y1, y2 = c[0] + u * d20, c[1] + u * d21, c[2] + u * d22
    n0, n1, n2, dist = _normalize(x0 - y0, x1 - y1, x2 - y2)
    if not dist > 0.0:
        dist = 0.0
        n0, n1, n2, m = _normalize(d11 * d22 - d12 * d21, d12 * d20 - d10 * d22, d10 * d21 - d11 * d20)
        if not m > 0.0:
            if aa > 0.0:
                n0, n1, n2 = _perpendicular(d10, d11, d12)
            else:
                n0, n1, n2 = _perpendicular(d20, d21, d22)
    return dist, s, n0, n1, n2


@njit(cache=True)
def _box_sq(al, d, half, t):
    """Squared distance from ``x(t) = al + t d`` (box frame) to the box ``|x_i| ≤ half_i``:
    ``Σ max(|x_i| − h_i, 0)²``."""
    acc = 0.0
    for i in range(3):
        g = abs(al[i] + t * d[i]) - half[i]
        if g > 0.0:
            acc += g * g
    return acc


@njit(cache=True)
def _excess(x, h):
    """``x − clamp(x, −h, h)``: how far the coordinate ``x`` is beyond the slab ``|x| ≤ h``, signed."""
    if x > h:
        return x - h
    if x < -h:
        return x + h
    return 0.0


@njit(cache=True)
def _box_breakpoint(k, al, d, half):
    """Breakpoint ``k`` of the piecewise quadratic, ``k = 0…7``: 0, 1, then ``t`` where ``x_i(t) = ±h_i``
    (``i = (k − 2) // 2``) — NaN when there is none strictly inside (0, 1)."""
    if k == 0:
        return 0.0
    if k == 1:
        return 1.0
    i = (k - 2) // 2
    if d[i] == 0.0:
        return np.nan
    h = half[i] if k % 2 == 0 else -half[i]
    t = (h - al[i]) / d[i]
    if t > 0.0 and t < 1.0:
        return t
    return np.nan


@njit(cache=True)
def _box_margin(al, d, half, t):
    """``(m, i)``: the margin ``min_i (h_i − |x_i(t)|)`` of ``x(t)`` inside the box and the axis attaining it."""
    best = np.inf
    arg = 0
    for i in range(3):
        g = half[i] - abs(al[i] + t * d[i])
        if g < best:
            best = g
            arg = i
    return best, arg


@njit(cache=True)
def _in_box(R, i, p, center):
    """Coordinate ``i`` of the point ``p`` in the box frame: ``(Rᵀ(p − center))_i`` (m)."""
    return R[0, i] * (p[0] - center[0]) + R[1, i] * (p[1] - center[1]) + R[2, i] * (p[2] - center[2])


@njit(cache=True)
def segment_box(a, b, center, R, half):
    """Signed distance from the segment ``a``–``b`` to the oriented box (``center``, ``R`` world ← box,
    half extents ``half``; m): ``(dist, t, n0, n1, n2)``.  Negative means the segment's axis is inside the box.

    Closed form, exact (no iteration).  In the box frame ``x(t) = Rᵀ(a − center) + t Rᵀ(b − a)`` and the
    squared distance ``f(t) = Σ max(|x_i(t)| − h_i, 0)²`` is convex and piecewise quadratic, with breakpoints
    where ``x_i(t) = ±h_i`` (at most 6 in (0, 1)).  On each piece between consecutive breakpoints the active
    faces are fixed (read at its midpoint; each piece's right end found by a scan, no sort or array), ``f`` is
    one quadratic whose vertex, clamped to the piece, is its minimum; the best piece gives ``t``.
    Outside: ``dist = |x − clamp(x)|`` and ``n = R (x − clamp(x))/dist``.

    Inside (``f(t) = 0``: the segment meets the box): ``dist = −pen``, ``pen`` the largest margin
    ``min_i (h_i − |x_i(t)|)`` over the part ``[t0, t1]`` of the segment inside the box.  That margin is the
    minimum of 6 linear functions of ``t``, concave, so its maximum is at ``t0``, ``t1`` or where two of them
    are equal: all those candidates are evaluated exactly.  ``t`` is the best candidate and ``n`` the outward
    normal (world) of the face with the least margin there (``∂dist/∂x = n`` again); of faces tied there, the
    one the segment runs most parallel to.  A segment touching the box gets ``dist = 0``."""
    al = (_in_box(R, 0, a, center), _in_box(R, 1, a, center), _in_box(R, 2, a, center))  # (tuples: no
    # allocation in the control tick, which calls this for every capsule–box pair)
    d = (_in_box(R, 0, b, center) - al[0], _in_box(R, 1, b, center) - al[1], _in_box(R, 2, b, center) - al[2])

    # Outside: minimise f over each piece [tl, tr] between consecutive breakpoints.
    t_best = 0.0
    f_best = _box_sq(al, d, half, 0.0)
    f1 = _box_sq(al, d, half, 1.0)
    if f1 < f_best:
        t_best, f_best = 1.0, f1
    for k in range(8):
        tl = _box_breakpoint(k, al, d, half)
        if not tl < 1.0:  # NaN (no breakpoint) or the right end
            continue
        tr = 1.0
        for j in range(2, 8):
            tj = _box_breakpoint(j, al, d, half)
            if tj > tl and tj < tr:
                tr = tj
        tm = 0.5 * (tl + tr)
        qa = 0.0
        qb = 0.0
        for i in range(3):
            xm = al[i] + tm * d[i]
            if xm > half[i]:
                qa += d[i] * d[i]
                qb += (al[i] - half[i]) * d[i]
            elif xm < -half[i]:
                qa += d[i] * d[i]
                qb += (al[i] + half[i]) * d[i]
        tv = tm  # no face active: f = 0 all along the piece (exactly so at its midpoint)
        if qa > 0.0:
            tv = -qb / qa
            if not tv > tl:
                tv = tl
            elif tv > tr:
                tv = tr
        fv = _box_sq(al, d, half, tv)
        if fv < f_best:
            t_best, f_best = tv, fv
        ft = _box_sq(al, d, half, tl)
        if ft < f_best:
            t_best, f_best = tl, ft

    if f_best > 0.0:
        v0 = _excess(al[0] + t_best * d[0], half[0])
        v1 = _excess(al[1] + t_best * d[1], half[1])
        v2 = _excess(al[2] + t_best * d[2], half[2])
        u0, u1, u2, dist = _normalize(v0, v1, v2)
        if dist > 0.0:
            n0 = R[0, 0] * u0 + R[0, 1] * u1 + R[0, 2] * u2
            n1 = R[1, 0] * u0 + R[1, 1] * u1 + R[1, 2] * u2
            n2 = R[2, 0] * u0 + R[2, 1] * u1 + R[2, 2] * u2
            return dist, t_best, n0, n1, n2

    # Inside: [t0, t1] = the part of the segment in the box (slab clipping), then the deepest point.
    t0 = 0.0
    t1 = 1.0
    for i in range(3):
        if d[i] != 0.0:
            ta = (-half[i] - al[i]) / d[i]
            tb = (half[i] - al[i]) / d[i]
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
    if not t0 <= t1:  # rounding at a touching segment
        t0 = t_best
        t1 = t_best
    pen, face = _box_margin(al, d, half, t_best)
    t_pen = t_best
    m, ax = _box_margin(al, d, half, t0)
    if m > pen:
        pen, face, t_pen = m, ax, t0
    m, ax = _box_margin(al, d, half, t1)
    if m > pen:
        pen, face, t_pen = m, ax, t1
    # Then where two margin lines l_k(t) = p_k + q_k t cross, faces k = 2i + (s < 0): p_k = h_i − s al_i,
    # q_k = −s d_i.
    for k in range(6):
        ik = k // 2
        sk = 1.0 if k % 2 == 0 else -1.0
        pk = half[ik] - sk * al[ik]
        qk = -sk * d[ik]
        for j in range(k + 1, 6):
            ij = j // 2
            sj = 1.0 if j % 2 == 0 else -1.0
            pj = half[ij] - sj * al[ij]
            qj = -sj * d[ij]
            if qk == qj:
                continue
            tc = (pj - pk) / (qk - qj)
            if tc > t0 and tc < t1:
                m, ax = _box_margin(al, d, half, tc)
                if m > pen:
                    pen, face, t_pen = m, ax, tc
    # The face: least margin at t_pen; near-ties (a corner of the margin, rounding) go to the face the segment
    # runs most parallel to — at the end of a flat stretch that is the face binding all along it.
    tie = 1e-12 * (1.0 + max(half[0], half[1], half[2]))
    for i in range(3):
        g = half[i] - abs(al[i] + t_pen * d[i])
        if g <= pen + tie and abs(d[i]) < abs(d[face]):
            face = i
    xf = al[face] + t_pen * d[face]
    sgn = 1.0 if xf >= 0.0 else -1.0
    dist = -pen if pen > 0.0 else 0.0
    return dist, t_pen, sgn * R[0, face], sgn * R[1, face], sgn * R[2, face]


@njit(cache=True)
def segment_obstacle(a, b, kind, center, second, R, half, radius):
    """Signed distance from the segment ``a``–``b`` to an obstacle's SURFACE (m): ``(dist, t, n0, n1, n2)``,
    the core distance minus ``radius``, negative inside the obstacle.  The caller subtracts the link radius.

    ``kind``: :data:`SPHERE` (``center``, ``radius``; :func:`segment_point`), :data:`CAPSULE` (axis
    ``center``–``second``, ``radius``; :func:`segment_segment`) or :data:`BOX` (``center``, ``R``, ``half``,
    ``radius`` ignored; :func:`segment_box`).  Arguments the kind does not use are ignored."""
    if kind == SPHERE:
        dist, t, n0, n1, n2 = segment_point(a, b, center)
        return dist - radius, t, n0, n1, n2
    if kind == CAPSULE:
        dist, t, n0, n1, n2 = segment_segment(a, b, center, second)
        return dist - radius, t, n0, n1, n2
    if kind == BOX:
        return segment_box(a, b, center, R, half)
    raise ValueError("segment_obstacle: unknown obstacle kind")
