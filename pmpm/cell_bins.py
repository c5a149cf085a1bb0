"""A lattice of bins over a rank's owned cell centres, and the compiled point location on it.

Both the coupling's touched-pair search (``coupling/pairs.py``) and ``Mesh.find_owned_cells``
ask which cells have their centres near a point; the bins answer in a few memory reads, where a
k-d tree query cost half a microsecond a point and Python's loop over candidate columns more.

A convex cell holds a point when the point lies on the inner side of every face's plane, the
plane through the face's centre with its area vector turned outwards (away from the cell's vertex
mean), within 1e-10 × √(face area). The planes are computed as the cells are tested, not stored (a
mesh's planes would take 300 bytes a cell).
"""
from __future__ import annotations

import numpy as np
from numba import njit


class CellBins:
    """A lattice of cubic bins over the owned cell centres (CSR: ``start``, ``cells``), bins about
    ``width`` wide. Built once per mesh."""

    def __init__(self, centers: np.ndarray, width: float):
        self.lower = centers.min(axis=0, initial=0.0) if len(centers) else np.zeros(3)
        span = (centers.max(axis=0) - self.lower) if len(centers) else np.zeros(3)
        width = max(width, float(span.max(initial=0.0)) / 2000.0, 1e-300)
        # no more bins than about 4 per cell, whatever the grading
        while np.prod(np.floor(span / width) + 1) > 4 * max(len(centers), 1):
            width *= 1.5
        self.width = width
        self.counts = (np.floor(span / width) + 1).astype(np.int64)
        flat = self.bin_of(centers)
        self.cells = np.argsort(flat, kind="stable").astype(np.int64)
        self.start = np.searchsorted(flat[self.cells], np.arange(int(np.prod(self.counts)) + 1)).astype(np.int64)

    def bin_of(self, points: np.ndarray) -> np.ndarray:
        """(n,) the bin holding each point (clamped to the lattice), numbered along z fastest."""
        index = np.clip(((points - self.lower) / self.width).astype(np.int64), 0, self.counts - 1)
        return np.ravel_multi_index(index.T, self.counts) if len(points) else np.zeros(0, np.int64)


@njit(cache=True)
def bin_box(x, reach, lower, width, counts):
    """The lattice index range [lo, hi] (inclusive, per axis) of bins within ``reach`` of ``x``."""
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for d in range(3):
        lo[d] = max(int(np.floor((x[d] - reach - lower[d]) / width)), 0)
        hi[d] = min(int(np.floor((x[d] + reach - lower[d]) / width)), counts[d] - 1)
    return lo, hi


@njit(cache=True, inline="always")
def edge(xyz, a, b):
    """The vector from vertex a to vertex b, as three scalars."""
    return xyz[b, 0] - xyz[a, 0], xyz[b, 1] - xyz[a, 1], xyz[b, 2] - xyz[a, 2]


@njit(cache=True)
def holds(vertex_xyz, cell_vertices, faces, cell, point):
    """Whether the convex ``cell`` holds ``point`` (module docstring); ``faces`` (faces a cell, 3
    or 4): each face's corners as positions in a cell's vertex list (``mesh.CELL_FACES``).
    Written out in scalars: small numpy temporaries would be allocated on the heap."""
    n_faces, corners = faces.shape
    n_vertices = cell_vertices.shape[1]
    mx = my = mz = 0.0
    for v in range(n_vertices):
        q = cell_vertices[cell, v]
        mx += vertex_xyz[q, 0]
        my += vertex_xyz[q, 1]
        mz += vertex_xyz[q, 2]
    mx, my, mz = mx / n_vertices, my / n_vertices, mz / n_vertices
    for f in range(n_faces):
        a, b, c = cell_vertices[cell, faces[f, 0]], cell_vertices[cell, faces[f, 1]], cell_vertices[cell, faces[f, 2]]
        cx = vertex_xyz[a, 0] + vertex_xyz[b, 0] + vertex_xyz[c, 0]
        cy = vertex_xyz[a, 1] + vertex_xyz[b, 1] + vertex_xyz[c, 1]
        cz = vertex_xyz[a, 2] + vertex_xyz[b, 2] + vertex_xyz[c, 2]
        if corners == 3:   # the area vector: half the cross product of two edges, or of the diagonals
            ux, uy, uz = edge(vertex_xyz, a, b)
            wx, wy, wz = edge(vertex_xyz, a, c)
            cx, cy, cz = cx / 3.0, cy / 3.0, cz / 3.0
        else:
            d = cell_vertices[cell, faces[f, 3]]
            ux, uy, uz = edge(vertex_xyz, a, c)
            wx, wy, wz = edge(vertex_xyz, b, d)
            cx, cy, cz = (cx + vertex_xyz[d, 0]) / 4.0, (cy + vertex_xyz[d, 1]) / 4.0, (cz + vertex_xyz[d, 2]) / 4.0
        ax, ay, az = 0.5 * (uy * wz - uz * wy), 0.5 * (uz * wx - ux * wz), 0.5 * (ux * wy - uy * wx)
        if ax * (cx - mx) + ay * (cy - my) + az * (cz - mz) < 0.0:
            ax, ay, az = -ax, -ay, -az
        size = np.sqrt(ax * ax + ay * ay + az * az)
        height = ((point[0] - cx) * ax + (point[1] - cy) * ay + (point[2] - cz) * az) / size
        if not height <= 1e-10 * np.sqrt(size):
            return False
    return True


@njit(cache=True, inline="always")
def distance2(point, centers, c):
    """|point − centers[c]|² (m²)."""
    dx, dy, dz = point[0] - centers[c, 0], point[1] - centers[c, 1], point[2] - centers[c, 2]
    return dx * dx + dy * dy + dz * dz


@njit(cache=True)
def bins_within(point, reach, bin_lower, bin_width, bin_counts):
    """The flat numbers of the bins within ``reach`` of ``point`` (at most the box of bins around it)."""
    lo, hi = bin_box(point, reach, bin_lower, bin_width, bin_counts)
    found = np.empty(max((hi[0] - lo[0] + 1) * (hi[1] - lo[1] + 1) * (hi[2] - lo[2] + 1), 0), np.int64)
    k = 0
    for bx in range(lo[0], hi[0] + 1):
        for by in range(lo[1], hi[1] + 1):
            for bz in range(lo[2], hi[2] + 1):
                found[k] = (bx * bin_counts[1] + by) * bin_counts[2] + bz
                k += 1
    return found


@njit(cache=True)
def holding_cells(vertex_xyz, cell_vertices, faces, centers, reach, bin_lower, bin_width, bin_counts,
                  bin_start, bin_cells, points):
    """(m,) the owned cell holding each of ``points`` (m, 3), or -1: of the cells whose centres lie
    within ``reach`` (the largest circumradius) of the point, the nearest centre's is tested
    first (it holds the point on regular meshes), then the others in bin order, so a point on a
    shared face goes to the first that holds it."""
    found = np.full(len(points), -1, np.int64)
    reach2 = reach * reach
    for i in range(len(points)):
        point = points[i]
        bins = bins_within(point, reach, bin_lower, bin_width, bin_counts)
        nearest, nearest2 = -1, np.inf
        for b in bins:
            for c in bin_cells[bin_start[b]:bin_start[b + 1]]:
                d2 = distance2(point, centers, c)
                if d2 <= reach2 and d2 < nearest2:
                    nearest, nearest2 = c, d2
        if nearest < 0 or holds(vertex_xyz, cell_vertices, faces, nearest, point):
            found[i] = nearest
            continue
        for b in bins:
            for c in bin_cells[bin_start[b]:bin_start[b + 1]]:
                if found[i] < 0 and c != nearest and distance2(point, centers, c) <= reach2 and \
                        holds(vertex_xyz, cell_vertices, faces, c, point):
                    found[i] = c
    return found
