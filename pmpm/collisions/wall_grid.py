"""A uniform grid of the wall triangles, compiled (numba): which triangles may be near a point,
and which one a straight path crosses first (stage 8's test for particles that left the domain).

Each triangle is listed in every cell its bounding box overlaps (CSR: ``start`` per cell, then
triangle indices); a point with a reach visits the cells its own box overlaps and keeps the
triangles whose bounding spheres meet its sphere, a path the cells of its box. Built once per
``Walls`` and cell size (a moved wall is a new ``Walls``), in O(triangles); a query costs
O(points × triangles per cell).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .contact_times import cross, dot, sub, vec


@njit(cache=True)
def cell_range(low, high, lower, cell, dims):
    """The cell index ranges (inclusive) of the box [low, high] in each axis, clamped to the grid:
    a box beyond the grid's last cell gets that cell (the triangles on the grid's upper faces,
    whose index comes out as ``dims``, and points beyond them; the sphere tests sort them out).
    Two 3-tuples (first, last): no arrays allocated (one query per particle and step)."""
    return ((cell_of(low[0], lower[0], cell, dims[0]), cell_of(low[1], lower[1], cell, dims[1]),
             cell_of(low[2], lower[2], cell, dims[2])),
            (cell_of(high[0], lower[0], cell, dims[0]), cell_of(high[1], lower[1], cell, dims[1]),
             cell_of(high[2], lower[2], cell, dims[2])))


@njit(cache=True)
def cell_of(value, lower, cell, size):
    """The cell along one axis holding ``value``, clamped to [0, size − 1]."""
    return min(max(int(np.floor((value - lower) / cell)), 0), size - 1)


@njit(cache=True)
def build(a, b, c, lower, cell, dims):
    """CSR of the triangles per cell: (start (cells + 1,), triangle indices)."""
    m = len(a)
    cells = dims[0] * dims[1] * dims[2]
    count = np.zeros(cells + 1, np.int64)
    for pass_ in range(2):
        if pass_ == 1:
            for k in range(cells):
                count[k + 1] += count[k]
            items = np.empty(count[cells], np.int64)
            fill = count[:cells].copy()
        for k in range(m):
            low = np.minimum(np.minimum(a[k], b[k]), c[k])
            high = np.maximum(np.maximum(a[k], b[k]), c[k])
            first, last = cell_range(low, high, lower, cell, dims)
            for i in range(first[0], last[0] + 1):
                for j in range(first[1], last[1] + 1):
                    for h in range(first[2], last[2] + 1):
                        index = (i * dims[1] + j) * dims[2] + h
                        if pass_ == 0:
                            count[index + 1] += 1
                        else:
                            items[fill[index]] = k
                            fill[index] += 1
    return count, items


@njit(cache=True)
def triangles_in_box(low, high, lower, cell, dims, start, items, seen, tag, out):
    """The triangles listed in the cells the box [low, high] overlaps, each once: written to
    ``out`` (as long as the triangles), their count returned. ``seen`` (per triangle) marks the
    triangles listed for ``tag`` (the query's number: no clearing between queries)."""
    first, last = cell_range(low, high, lower, cell, dims)
    count = 0
    for i in range(first[0], last[0] + 1):
        for j in range(first[1], last[1] + 1):
            for h in range(first[2], last[2] + 1):
                index = (i * dims[1] + j) * dims[2] + h
                for at in range(start[index], start[index + 1]):
                    k = items[at]
                    if seen[k] != tag:
                        seen[k] = tag
                        out[count] = k
                        count += 1
    return count


@njit(cache=True)
def near(points, reach, extra, extra_max, lower, cell, dims, start, items, box_low, box_high, centroid, bound):
    """(point, triangle) index pairs that may come within ``reach`` (per point, m) of each other
    when the triangle moves by up to ``extra`` (per triangle, m): their bounding boxes meet and
    their bounding spheres meet (|p − centroid| <= reach_p + bound_k + extra_k), both necessary.
    Sorted by point, then triangle. ``extra_max`` widens the cells visited."""
    n = len(points)
    seen = np.full(len(centroid), -1, np.int64)
    listed = np.empty(len(centroid), np.int64)
    capacity = 16 * n + 16
    found_p = np.empty(capacity, np.int64)
    found_k = np.empty(capacity, np.int64)
    count = 0
    low = np.empty(3)
    high = np.empty(3)
    for p in range(n):
        for d in range(3):
            low[d] = points[p, d] - reach[p] - extra_max
            high[d] = points[p, d] + reach[p] + extra_max
        begin = count
        for at in range(triangles_in_box(low, high, lower, cell, dims, start, items, seen, p, listed)):
            k = listed[at]
            grow = reach[p] + extra[k]
            apart = False
            for d in range(3):
                apart |= (box_low[k, d] - grow > points[p, d]) or (box_high[k, d] + grow < points[p, d])
            if apart:
                continue
            d0 = points[p, 0] - centroid[k, 0]
            d1 = points[p, 1] - centroid[k, 1]
            d2 = points[p, 2] - centroid[k, 2]
            limit = grow + bound[k]
            if d0 * d0 + d1 * d1 + d2 * d2 > limit * limit:
                continue
            if count == capacity:
                capacity *= 2
                grown_p = np.empty(capacity, np.int64)
                grown_k = np.empty(capacity, np.int64)
                grown_p[:count] = found_p[:count]
                grown_k[:count] = found_k[:count]
                found_p, found_k = grown_p, grown_k
            found_p[count] = p
            found_k[count] = k
            count += 1
        for at in range(begin + 1, count):  # the few triangles of p in order (insertion, in place)
            k = found_k[at]
            back = at - 1
            while back >= begin and found_k[back] > k:
                found_k[back + 1] = found_k[back]
                back -= 1
            found_k[back + 1] = k
    return found_p[:count].copy(), found_k[:count].copy()


@njit(cache=True)
def first_crossings(start, end, lower, cell, dims, cell_start, items, a, b, c, normal, box_low, box_high, tolerance):
    """For each path from ``start`` to ``end`` (n, 3), the triangle it crosses first going against
    the triangle's inward ``normal``, or −1 (a path that is not finite or has no length crosses none).
    Möller–Trumbore, s + t d = a + u (b − a) + v (c − a), with u, v ≥ −tol, u + v ≤ 1 + tol and
    t in [−tol, 1 + tol]: a path through an edge or a vertex hits a triangle."""
    seen = np.full(len(a), -1, np.int64)
    listed = np.empty(len(a), np.int64)
    out = np.full(len(start), -1, np.int64)
    low = np.empty(3)
    high = np.empty(3)
    for p in range(len(start)):
        s = vec(start, p)
        d = sub(vec(end, p), s)
        if not (np.isfinite(d[0]) and np.isfinite(d[1]) and np.isfinite(d[2])) or dot(d, d) == 0.0:
            continue
        for i in range(3):
            low[i] = min(start[p, i], end[p, i])
            high[i] = max(start[p, i], end[p, i])
        best = np.inf
        for at in range(triangles_in_box(low, high, lower, cell, dims, cell_start, items, seen, p, listed)):
            k = listed[at]
            apart = False
            for e in range(3):
                apart |= (box_low[k, e] > high[e]) or (box_high[k, e] < low[e])
            if apart or dot(d, vec(normal, k)) >= 0.0:
                continue   # inwards, or along the face
            t = crossing(s, d, vec(a, k), vec(b, k), vec(c, k), tolerance)
            if t < best:
                best, out[p] = t, k
    return out


@njit(cache=True)
def crossing(s, d, a, b, c, tolerance):
    """The path fraction t at which s + t d crosses the triangle (a, b, c), or inf (``first_crossings``)."""
    e1, e2 = sub(b, a), sub(c, a)
    q = cross(d, e2)
    det = dot(e1, q)
    if det == 0.0:
        return np.inf
    offset = sub(s, a)
    u = dot(offset, q) / det
    if u < -tolerance or u > 1.0 + tolerance:
        return np.inf
    r = cross(offset, e1)
    v = dot(d, r) / det
    if v < -tolerance or u + v > 1.0 + tolerance:
        return np.inf
    t = dot(e2, r) / det
    return t if -tolerance <= t <= 1.0 + tolerance else np.inf
