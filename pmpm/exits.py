"""Which boundary a particle left the domain through: the first boundary face its centre's path
over the step (a straight line from where it started the step to where it ended) crosses, or,
where the path crosses none to round-off, the face nearest to where it ended. Counted per
boundary in summary.json (``particles_removed_through``), so a run shows that particles leave
only where they may (a hopper's orifice, a pipe's outlet) and never through a wall.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .collisions import jit

ROWS_PER_CHUNK = 250_000   # point–triangle pairs measured at once (bounds the memory, ≈ 0.1 GB)


@dataclass(frozen=True)
class ExitFaces:
    """Every boundary triangle of the mesh, the same on every rank.

    triangles : (m, 3, 3) vertex coordinates (m); boundary : (m,) index into ``names``
    names : the mesh's boundary names
    lower, upper : (m, 3) each triangle's box, grown by a millionth of the mesh's extent (m)
    """

    triangles: np.ndarray
    boundary: np.ndarray
    names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def of_mesh(cls, mesh) -> "ExitFaces":
        """Collective. The boundary triangles of ``mesh``."""
        triangles, boundary, _ = mesh.boundary_triangles(mesh.boundary_names)
        triangles = np.reshape(triangles, (-1, 3, 3))
        pad = 1e-6 * float(np.ptp(triangles.reshape(-1, 3), axis=0).max()) if len(triangles) else 0.0
        return cls(triangles, np.asarray(boundary, np.int64), tuple(mesh.boundary_names),
                   triangles.min(axis=1, initial=np.inf) - pad, triangles.max(axis=1, initial=-np.inf) + pad)

    def nearest(self, points: np.ndarray) -> np.ndarray:
        """(k,) index into ``names`` of the boundary nearest to each point (k, 3) (m)."""
        points = np.asarray(points, float).reshape(-1, 3)
        if len(self.triangles) == 0 or len(points) == 0:
            return np.zeros(len(points), np.int64)
        a, b, c = self.triangles[:, 0], self.triangles[:, 1], self.triangles[:, 2]
        face, _ = jit.kernels().contact_times.nearest_faces(points, a, b, c)
        return self.boundary[face]

    def crossed(self, start: np.ndarray, end: np.ndarray) -> np.ndarray:
        """(k,) index into ``names`` of the boundary that each path from ``start`` (k, 3), inside,
        to ``end`` (k, 3), outside, crosses first; the nearest to ``end`` where it crosses none."""
        start, end = np.asarray(start, float).reshape(-1, 3), np.asarray(end, float).reshape(-1, 3)
        out = np.full(len(start), -1, np.int64)
        if len(self.triangles) == 0 or len(start) == 0:
            return np.zeros(len(start), np.int64)
        # only the faces whose box meets the paths' box (a hopper's orifice, not the whole wall)
        low, high = np.minimum(start, end).min(axis=0), np.maximum(start, end).max(axis=0)
        near = np.flatnonzero(((self.lower <= high) & (self.upper >= low)).all(axis=1))
        triangles, boundary, m = self.triangles[near], self.boundary[near], len(near)
        a = triangles[:, 0]
        e1, e2 = triangles[:, 1] - a, triangles[:, 2] - a
        per_chunk = max(1, ROWS_PER_CHUNK // max(m, 1))
        for first in range(0, len(start), per_chunk) if m else ():
            s, d = start[first:first + per_chunk, None, :], (end - start)[first:first + per_chunk, None, :]
            # Möller–Trumbore: s + t d = a + u e1 + v e2, 0 ≤ t ≤ 1, u, v ≥ 0, u + v ≤ 1
            p = np.cross(d, e2)
            det = np.sum(e1 * p, axis=-1)
            inverse = 1.0 / np.where(det == 0, np.inf, det)    # a path parallel to a face misses it
            offset = s - a
            u = np.sum(offset * p, axis=-1) * inverse
            q = np.cross(offset, e1)
            v = np.sum(d * q, axis=-1) * inverse
            t = np.sum(e2 * q, axis=-1) * inverse
            tol = 1e-9
            hit = (det != 0) & (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol) & (t >= -tol) & (t <= 1 + tol)
            t = np.where(hit, t, np.inf)
            nearest_hit = np.argmin(t, axis=1)
            any_hit = np.isfinite(t[np.arange(len(t)), nearest_hit])
            rows = first + np.flatnonzero(any_hit)
            out[rows] = boundary[nearest_hit[any_hit]]
        missed = out < 0
        out[missed] = self.nearest(end[missed])
        return out

    def count(self, start: np.ndarray, end: np.ndarray, totals: dict) -> dict:
        """``totals`` (boundary name → particles) with the particles that went from ``start`` to
        ``end`` (outside) added, each to the boundary it crossed (``crossed``)."""
        index, counts = np.unique(self.crossed(start, end), return_counts=True)
        totals = dict(totals)
        for i, n in zip(index.tolist(), counts.tolist()):
            totals[self.names[i]] = totals.get(self.names[i], 0) + int(n)
        return totals
