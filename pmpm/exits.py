"""Stage 8's test for particles that left the domain, the same on every rank count: a particle
leaves when the path of its centre over the step (a straight line from where it started the step
to where it ended) crosses a boundary triangle of the mesh outwards, and it is counted through the
first one crossed (``particles_removed_through`` in summary.json, so a run shows that particles
leave only where they may: a hopper's orifice, a pipe's outlet). Through an outlet this is how
particles leave; through a wall it catches a sphere that tunnelled (it is removed and counted
through the wall, never left flying outside the mesh); without [collisions] every boundary lets
particles through.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .collisions.jit import kernels
from .collisions.walls import Walls

TOLERANCE = 1e-9   # barycentric and path-fraction slack: a path through an edge or a vertex hits a triangle


@dataclass(frozen=True)
class BoundaryFaces:
    """Every boundary triangle of the mesh, the same on every rank.

    triangles : ``Walls`` holding the triangles (for their geometry, inward normal and search grid)
    names : the mesh's boundary names, indexed by ``triangles.boundary``
    """

    triangles: Walls
    names: tuple[str, ...]

    @classmethod
    def of_mesh(cls, mesh) -> "BoundaryFaces":
        """Collective. The boundary triangles of ``mesh``."""
        triangles, boundary, normal = mesh.boundary_triangles(mesh.boundary_names)
        walls = Walls.from_triangles(np.reshape(triangles, (-1, 3, 3)), normal, boundary)
        return cls(walls, tuple(mesh.boundary_names))

    def crossed(self, start: np.ndarray, end: np.ndarray) -> np.ndarray:
        """Local. (k,) index into ``names`` of the boundary that each path from ``start`` (k, 3) to
        ``end`` (k, 3) crosses outwards first, or −1 where it crosses none (or is not finite)."""
        start, end = np.asarray(start, float).reshape(-1, 3), np.asarray(end, float).reshape(-1, 3)
        if len(start) == 0 or len(self.triangles) == 0:
            return np.full(len(start), -1, np.int64)
        walls = self.triangles
        lower, cell, dims, cell_start, items = walls.grid()   # (a step's paths are short)
        triangle = kernels().wall_grid.first_crossings(np.ascontiguousarray(start), np.ascontiguousarray(end), lower,
                                                       cell, dims, cell_start, items, walls.a, walls.b, walls.c,
                                                       walls.normal, *walls.box, TOLERANCE)
        return np.where(triangle >= 0, walls.boundary[triangle], -1)

    def count(self, crossed: np.ndarray) -> dict:
        """Boundary name → particles, of the boundaries in ``crossed`` (indices into ``names``, as
        from ``crossed``, each one particle)."""
        index, counts = np.unique(crossed, return_counts=True)
        return {self.names[i]: int(n) for i, n in zip(index.tolist(), counts.tolist())}
