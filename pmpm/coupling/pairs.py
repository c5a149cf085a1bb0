"""The touched pairs of a step, compiled (numba; loaded by the first coupled step): for each
particle, the owned cells whose centres lie within its radius plus their reach, found through a
lattice of bins over the cell centres, with its volume fraction α and smooth fraction in each.
One pass over the particles without Python lists or (pairs, vertices, 3) temporaries: in a dense
bed at 3 cells per diameter this search was half of the coupling's time (docs/coupling.md).

α by the ``nodes`` rule is the share of the cell's vertices inside the sphere; by the ``subcell``
rule the share of k³ sample points inside. For hexahedra the samples lie on k² straight lines
(a trilinear map is linear along each of its parameters), so each line's count comes from where
it enters and leaves the sphere, one square root instead of k point tests.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ..cell_bins import bin_box

NODES, SUBCELL_HEX, SUBCELL_SAMPLED = 0, 1, 2


@njit(cache=True, inline="always")
def _line_count(x0, y0, z0, x1, y1, z1, k, r2):
    """How many of the k points p0 + t (p1 − p0), t = (i + ½)/k, lie in the ball |p|² ≤ r2
    (p0, p1 relative to the centre)."""
    dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
    a = dx * dx + dy * dy + dz * dz
    b = x0 * dx + y0 * dy + z0 * dz
    c = x0 * x0 + y0 * y0 + z0 * z0 - r2
    if a <= 0.0:
        return k if c <= 0.0 else 0
    disc = b * b - a * c
    if disc < 0.0:
        return 0
    root = np.sqrt(disc)
    first = max(int(np.ceil((-b - root) / a * k - 0.5)), 0)
    last = min(int(np.floor((-b + root) / a * k - 0.5)), k - 1)
    return max(last - first + 1, 0)


@njit(cache=True)
def _fraction(rule, gap, inside_count, n_vertices, weights, k, r2):
    """α of one cell from its vertices relative to the sphere's centre, ``gap`` (nv, 3)."""
    if rule == NODES:
        return inside_count / n_vertices
    if inside_count == n_vertices:
        return 1.0
    if rule == SUBCELL_HEX:
        # PETSc's hex order: bottom (0,0) (0,1) (1,1) (1,0) in (a, b); top (0,0) (1,0) (1,1) (0,1)
        count = 0
        for i in range(k):
            a = (i + 0.5) / k
            for j in range(k):
                b = (j + 0.5) / k
                w00, w01, w11, w10 = (1 - a) * (1 - b), (1 - a) * b, a * b, a * (1 - b)
                count += _line_count(
                    w00 * gap[0, 0] + w01 * gap[1, 0] + w11 * gap[2, 0] + w10 * gap[3, 0],
                    w00 * gap[0, 1] + w01 * gap[1, 1] + w11 * gap[2, 1] + w10 * gap[3, 1],
                    w00 * gap[0, 2] + w01 * gap[1, 2] + w11 * gap[2, 2] + w10 * gap[3, 2],
                    w00 * gap[4, 0] + w10 * gap[5, 0] + w11 * gap[6, 0] + w01 * gap[7, 0],
                    w00 * gap[4, 1] + w10 * gap[5, 1] + w11 * gap[6, 1] + w01 * gap[7, 1],
                    w00 * gap[4, 2] + w10 * gap[5, 2] + w11 * gap[6, 2] + w01 * gap[7, 2], k, r2)
        return count / (k * k * k)
    count = 0
    n_samples = weights.shape[0]
    for s in range(n_samples):
        px = 0.0
        py = 0.0
        pz = 0.0
        for v in range(n_vertices):
            w = weights[s, v]
            px += w * gap[v, 0]
            py += w * gap[v, 1]
            pz += w * gap[v, 2]
        if px * px + py * py + pz * pz <= r2:
            count += 1
    return count / n_samples


@njit(cache=True)
def touched_pairs(x, radius, candidates, bin_lower, bin_width, bin_counts, bin_start, bin_cells,
                  cell_center, cell_reach, search_reach, h, vertex_xyz, cell_vertices,
                  rule, weights, k, keep_smooth):
    """The (particle, cell) pairs of the ``candidates`` particles: (particle, cell) int64, α and the
    smooth fraction (each (m,)), a pair kept where α > 0 (or, ``keep_smooth``, its smooth fraction
    is > 0).

    The smooth fraction is a linear ramp of the cell centre's distance to the sphere's surface
    over the cell's extent along the normal, h Σ|n_i| (exact for a plane cutting a cube).
    Cells whose centre lies farther than the radius plus ``search_reach`` (per cell: its
    ``cell_reach``, the centre's largest distance to a vertex, and with ``keep_smooth`` at least
    half the largest extent, √3 h/2) are neither. A convex cell with every vertex inside the
    sphere has α = 1; one farther than the radius plus ``cell_reach`` has α = 0.
    """
    n_vertices = cell_vertices.shape[1]
    largest = search_reach.max()
    bound = 0           # the cells within reach: the arrays' size (a pass of distances, ~10 % of the time)
    for i in range(len(candidates)):
        p = candidates[i]
        lo, hi = bin_box(x[p], radius[p] + largest, bin_lower, bin_width, bin_counts)
        for bx in range(lo[0], hi[0] + 1):
            for by in range(lo[1], hi[1] + 1):
                for bz in range(lo[2], hi[2] + 1):
                    b = (bx * bin_counts[1] + by) * bin_counts[2] + bz
                    for s in range(bin_start[b], bin_start[b + 1]):
                        c = bin_cells[s]
                        dx = cell_center[c, 0] - x[p, 0]
                        dy = cell_center[c, 1] - x[p, 1]
                        dz = cell_center[c, 2] - x[p, 2]
                        reach = radius[p] + search_reach[c]
                        if dx * dx + dy * dy + dz * dz < reach * reach:
                            bound += 1
    particle = np.empty(bound, np.int64)
    cell = np.empty(bound, np.int64)
    alpha = np.empty(bound)
    smooth = np.empty(bound)
    gap = np.empty((n_vertices, 3))
    m = 0
    for i in range(len(candidates)):
        p = candidates[i]
        r = radius[p]
        r2 = r * r
        lo, hi = bin_box(x[p], r + largest, bin_lower, bin_width, bin_counts)
        for bx in range(lo[0], hi[0] + 1):
            for by in range(lo[1], hi[1] + 1):
                for bz in range(lo[2], hi[2] + 1):
                    b = (bx * bin_counts[1] + by) * bin_counts[2] + bz
                    for s in range(bin_start[b], bin_start[b + 1]):
                        c = bin_cells[s]
                        dx = cell_center[c, 0] - x[p, 0]
                        dy = cell_center[c, 1] - x[p, 1]
                        dz = cell_center[c, 2] - x[p, 2]
                        d2 = dx * dx + dy * dy + dz * dz
                        reach = r + search_reach[c]
                        if d2 >= reach * reach:
                            continue
                        distance = max(np.sqrt(d2), 1e-300)
                        extent = max(h[c] * (abs(dx) + abs(dy) + abs(dz)) / distance, 1e-300)
                        ramp = min(max(0.5 - (distance - r) / extent, 0.0), 1.0)
                        a = 0.0
                        near = r + cell_reach[c]
                        if d2 < near * near:
                            inside_count = 0
                            for v in range(n_vertices):
                                for d in range(3):
                                    gap[v, d] = vertex_xyz[cell_vertices[c, v], d] - x[p, d]
                                if gap[v, 0] * gap[v, 0] + gap[v, 1] * gap[v, 1] + gap[v, 2] * gap[v, 2] <= r2:
                                    inside_count += 1
                            a = _fraction(rule, gap, inside_count, n_vertices, weights, k, r2)
                        if a > 0.0 or (keep_smooth and ramp > 0.0):
                            particle[m] = p
                            cell[m] = c
                            alpha[m] = a
                            smooth[m] = ramp
                            m += 1
    return particle[:m], cell[:m], alpha[:m], smooth[:m]
