"""Which owned cells each particle touches, and its volume fraction α in each (paper Figure 1).

A cell is *touched* when one of its vertices lies in the sphere (the paper); with the ``subcell``
rule, or for the penalty's smooth fractions, cells up to one cell diameter beyond the sphere count
too, since a sphere can cut a cell without holding one of its vertices. Rules for α
(``[coupling] volume_fraction``): ``nodes``, the share of the cell's vertices inside (the paper);
``subcell``, the share of k³ sample points of the cell inside. Each pair also carries a smooth
fraction, a linear ramp of the cell centre's distance to the sphere's surface over the cell's
extent along the normal (h Σ|n_i|, exact for a plane cutting a cube), which varies smoothly as the
particle moves: the penalty weighs the fluid under a particle by it. The search is compiled
(``pairs.py``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..particles import ParticleState


@dataclass(frozen=True)
class Touched:
    """(particle, owned cell) pairs of one step on this rank, (m,) int64 each, with the particle's
    volume fraction α of the cell and its smooth fraction (the module docstring), (m,) each."""

    particle: np.ndarray
    cell: np.ndarray
    alpha: np.ndarray
    smooth: np.ndarray

    @classmethod
    def empty(cls) -> "Touched":
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))


class CellLocator:
    """The touched cells of particles on this rank's owned cells. Built once per mesh (a lattice
    of bins over the owned cell centres, ``cell_bins.CellBins``); ``locate`` is local and compiled
    (``pairs.touched_pairs``).

    Parameters
    ----------
    mesh : pmpm.mesh.Mesh
    rule : "nodes" or "subcell"
    subcell_points : k of the subcell rule (k³ sample points per cell)
    smooth_reach : the forcing weighs cells by their smooth fraction too (the penalty): keep the
        cells beyond the sphere that it reaches
    """

    def __init__(self, mesh, rule: str, subcell_points: int, smooth_reach: bool):
        from ..cell_bins import CellBins
        from .pairs import NODES, SUBCELL_HEX, SUBCELL_SAMPLED
        self.mesh, self.smooth_reach = mesh, smooth_reach
        n_owned = mesh.n_owned_cells
        centers = mesh.cell_center[:n_owned]
        corners = mesh.vertex_xyz[mesh.cell_vertices[:n_owned]]
        self.lower = corners.reshape(-1, 3).min(axis=0, initial=np.inf)
        self.upper = corners.reshape(-1, 3).max(axis=0, initial=-np.inf)
        self.h = mesh.cell_volume[:n_owned] ** (1 / 3)     # the cell size h
        self.h2 = self.h ** 2
        self.cell_reach = np.linalg.norm(corners - centers[:, None, :], axis=2).max(axis=1, initial=0)
        # the smooth fraction reaches half the cell's extent along the normal, at most √3 h/2
        self.search_reach = np.maximum(self.cell_reach, 0.5 * np.sqrt(3.0) * self.h) if smooth_reach \
            else self.cell_reach
        self.bins = CellBins(centers, float(np.median(self.h)) if n_owned else 1.0)
        self.subcell_points = int(subcell_points)
        if rule == "nodes":
            self.rule, self.samples = NODES, np.zeros((1, mesh.cell_vertices.shape[1]))
        elif mesh.cell_type == "hex":
            self.rule, self.samples = SUBCELL_HEX, np.zeros((1, mesh.cell_vertices.shape[1]))
        else:
            self.rule, self.samples = SUBCELL_SAMPLED, reference_samples(mesh.cell_type, self.subcell_points)

    def locate(self, state: ParticleState) -> Touched:
        """Local. The owned cells each particle touches, with its volume fraction α in each."""
        from .pairs import touched_pairs
        reach = state.radius + self.search_reach.max(initial=0.0)
        near = np.all((state.x + reach[:, None] >= self.lower) & (state.x - reach[:, None] <= self.upper), axis=1)
        candidates = np.flatnonzero(near)
        if len(candidates) == 0:
            return Touched.empty()
        mesh, bins = self.mesh, self.bins
        # neighbours in turn: they share cells and vertices in the cache (2× faster in a bed)
        candidates = candidates[np.argsort(bins.bin_of(state.x[candidates]), kind="stable")]
        return Touched(*touched_pairs(
            np.ascontiguousarray(state.x, float), np.ascontiguousarray(state.radius, float), candidates.astype(np.int64),
            bins.lower, bins.width, bins.counts, bins.start, bins.cells, mesh.cell_center, self.cell_reach,
            self.search_reach, self.h, mesh.vertex_xyz, mesh.cell_vertices, self.rule, self.samples,
            self.subcell_points, self.smooth_reach))


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


def shared_smooth(touched: Touched, n_owned: int) -> np.ndarray:
    """The smooth fraction of each (particle, cell) pair, shared like α where particles overlap: a
    volume fraction that varies smoothly with the particle's position (``Touched.smooth``)."""
    total = np.bincount(touched.cell, touched.smooth, minlength=n_owned)
    return touched.smooth / np.maximum(total[touched.cell], 1.0)


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
