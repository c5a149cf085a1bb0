"""Which owned cells each particle touches, and its volume fraction α in each (paper Figure 1).

A cell is *touched* when one of its vertices lies in the sphere (the paper); with the ``subcell``
rule, or for the penalty's smooth fractions, cells up to one cell diameter beyond the sphere count
too, since a sphere can cut a cell without holding one of its vertices. Rules for α
(``[coupling] volume_fraction``): ``nodes``, the share of the cell's vertices inside (the paper);
``subcell``, the share of k³ sample points of the cell inside.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

from ..particles import ParticleState


@dataclass(frozen=True)
class Touched:
    """(particle, owned cell, α) triples of one step on this rank: (m,) int64, (m,) int64, (m,)."""

    particle: np.ndarray
    cell: np.ndarray
    alpha: np.ndarray

    @classmethod
    def empty(cls) -> "Touched":
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))


class CellLocator:
    """The touched cells of particles on this rank's owned cells. Built once per mesh (a k-d tree
    over the owned cells' vertices and the vertex → cell incidence); ``locate`` is local.

    Parameters
    ----------
    mesh : pmpm.mesh.Mesh
    rule : "nodes" or "subcell"
    subcell_points : k of the subcell rule (k³ sample points per cell)
    smooth_reach : the forcing weighs cells by ``smooth_fraction`` too (the penalty): keep the cells
        beyond the sphere that it reaches
    """

    def __init__(self, mesh, rule: str, subcell_points: int, smooth_reach: bool):
        self.mesh, self.rule, self.smooth_reach = mesh, rule, smooth_reach
        n_owned = mesh.n_owned_cells
        owned_vertices = mesh.cell_vertices[:n_owned]
        self.vertices_per_cell = owned_vertices.shape[1]
        # only the vertices of owned cells, and which owned cells each belongs to
        used = np.unique(owned_vertices)
        self.tree = cKDTree(mesh.vertex_xyz[used], balanced_tree=False, compact_nodes=False)
        local = np.searchsorted(used, owned_vertices)
        self.incidence = scipy.sparse.csr_matrix(
            (np.ones(local.size), (local.ravel(), np.repeat(np.arange(n_owned), self.vertices_per_cell))),
            shape=(len(used), n_owned))
        xyz = mesh.vertex_xyz[used]
        self.lower = xyz.min(axis=0, initial=np.inf)
        self.upper = xyz.max(axis=0, initial=-np.inf)
        corners = mesh.vertex_xyz[owned_vertices]
        self.cell_diameter = float(np.linalg.norm(corners.max(axis=1) - corners.min(axis=1), axis=1).max(initial=0))
        self.h2 = mesh.cell_volume[:n_owned] ** (2 / 3)     # squared cell size h²
        self.cell_reach = np.linalg.norm(corners - mesh.cell_center[:n_owned, None, :], axis=2).max(axis=1, initial=0)
        self.samples = reference_samples(mesh.cell_type, subcell_points) if rule == "subcell" else None

    def locate(self, state: ParticleState) -> Touched:
        """Local. The owned cells each particle touches, with its volume fraction α in each."""
        extended = self.rule == "subcell" or self.smooth_reach
        reach = state.radius + (self.cell_diameter if extended else 0.0)
        near = np.all((state.x + reach[:, None] >= self.lower) & (state.x - reach[:, None] <= self.upper), axis=1)
        candidates = np.flatnonzero(near)
        if len(candidates) == 0:
            return Touched.empty()
        hits = self.tree.query_ball_point(state.x[candidates], reach[candidates])
        counts = np.fromiter((len(h) for h in hits), np.int64, len(hits))
        if counts.sum() == 0:
            return Touched.empty()
        rows = np.repeat(np.arange(len(candidates)), counts)
        columns = np.concatenate([np.asarray(h, np.int64) for h in hits if len(h)])
        inside = scipy.sparse.csr_matrix((np.ones(len(rows)), (rows, columns)),
                                         shape=(len(candidates), self.tree.n))
        per_cell = (inside @ self.incidence).tocoo()       # vertices inside, per (particle, cell)
        particle = candidates[per_cell.row]
        cell = per_cell.col.astype(np.int64)
        if not extended:
            return Touched(particle, cell, per_cell.data / self.vertices_per_cell)
        if self.rule == "nodes":
            alpha = self.vertex_fraction(state, particle, cell)
        else:
            alpha = self.sampled_fraction(state, particle, cell)
        keep = alpha > 0
        if self.smooth_reach:
            keep |= smooth_fraction(self.mesh, self.h2, state, Touched(particle, cell, alpha), shared=False) > 0
        return Touched(particle[keep], cell[keep], alpha[keep])

    def vertex_fraction(self, state, particle, cell) -> np.ndarray:
        """The paper's α: the share of the cell's vertices inside the sphere, per (particle, cell) pair."""
        gap = self.mesh.vertex_xyz[self.mesh.cell_vertices[cell]] - state.x[particle, None, :]
        return (np.einsum("mvd,mvd->mv", gap, gap) <= state.radius[particle, None] ** 2).mean(axis=1)

    def sampled_fraction(self, state, particle, cell) -> np.ndarray:
        """Share of the cell's k³ sample points inside the sphere, per (particle, cell) pair; only the
        cells the surface may cut are sampled (compiled: ``sampling.sampled_fraction``)."""
        from .sampling import sampled_fraction     # numba, loaded by the first sub-cell step
        mesh = self.mesh
        return sampled_fraction(self.samples, mesh.vertex_xyz, mesh.cell_vertices, mesh.cell_center, self.cell_reach,
                                state.x, state.radius, particle.astype(np.int64), cell.astype(np.int64))


def alpha_per_cell(touched: Touched, n_owned: int) -> np.ndarray:
    """(n_owned,) Σ α over the particles touching each owned cell (may exceed 1 where they overlap)."""
    return np.bincount(touched.cell, touched.alpha, minlength=n_owned)


def shared_alpha(touched: Touched, n_owned: int) -> np.ndarray:
    """α of each (particle, cell) pair, scaled down where overlapping particles cover a cell more
    than once, so that a cell is never forced beyond its own volume."""
    total = alpha_per_cell(touched, n_owned)
    return touched.alpha / np.maximum(total[touched.cell], 1.0)


def volume_fraction(touched: Touched, n_owned: int) -> np.ndarray:
    """(n_owned,) particle volume fraction per owned cell, at most 1."""
    return np.minimum(alpha_per_cell(touched, n_owned), 1.0)


def smooth_fraction(mesh, h2: np.ndarray, state: ParticleState, touched: Touched,
                    x: np.ndarray | None = None, shared: bool = True) -> np.ndarray:
    """A volume fraction of each (particle, cell) pair that varies smoothly with the particle's
    position: a linear ramp of the cell centre's distance to the sphere surface over the cell's
    extent along the normal (h Σ|n_i|, exact for a plane cutting a cube), shared like α.
    ``h2``: h² per owned cell (n_owned,); ``x``: the particles' centres, if not where ``state`` has them."""
    r = mesh.cell_center[touched.cell] - (state.x if x is None else x)[touched.particle]
    distance = np.maximum(np.linalg.norm(r, axis=1), 1e-300)
    extent = np.maximum(np.sqrt(h2[touched.cell]) * np.abs(r).sum(axis=1) / distance, 1e-300)
    fraction = np.clip(0.5 - (distance - state.radius[touched.particle]) / extent, 0.0, 1.0)
    if not shared:
        return fraction
    total = np.bincount(touched.cell, fraction, minlength=mesh.n_owned_cells)
    return fraction / np.maximum(total[touched.cell], 1.0)


def reference_samples(cell_type: str, k: int) -> np.ndarray:
    """Weights (k³, n_vertices) that map a cell's vertices to k³ evenly spread sample points."""
    t = (np.arange(k) + 0.5) / k
    a, b, c = [g.ravel() for g in np.meshgrid(t, t, t, indexing="ij")]
    if cell_type == "hex":
        # trilinear map; PETSc vertex order (0,0,0) (0,1,0) (1,1,0) (1,0,0) (0,0,1) (1,0,1) (1,1,1) (0,1,1)
        corners = np.array([(0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)])
        x = np.stack([a, b, c], axis=1)
        return np.prod(np.where(corners[None, :, :] == 1, x[:, None, :], 1 - x[:, None, :]), axis=2)
    # tetrahedron: sorting the coordinates of a point of the unit cube folds the cube's 6 Kuhn
    # tetrahedra onto one, so an even cube lattice becomes an even tetrahedron sampling
    s = -np.sort(-np.stack([a, b, c], axis=1), axis=1)
    return np.stack([1 - s[:, 0], s[:, 0] - s[:, 1], s[:, 1] - s[:, 2], s[:, 2]], axis=1)
