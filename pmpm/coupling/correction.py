"""A drag correction for under-resolved particles (``[coupling] drag_correction``, default off).

On a few cells per diameter the flow through the gaps between particles is not resolved: a packed
bed's pores are about a cell wide, and its pressure drop comes out too low (at 3 cells per diameter
0.39 of Ergun's at Re 1, 0.85 at Re 500; docs/coupling.md, "Dense suspensions"). The correction
brings each particle's drag up to a correlation for spheres among spheres at the local voidage
(Di Felice 1994, or Beetstra, van der Hoef & Kuipers 2007), adding only what the resolved drag lacks:

- the local voidage ε and fluid velocity u_f are averages over a lattice of filter bins (``filter``
  wide, default 3 diameters), interpolated to each particle's centre; the slip is U_s = ε (u_f − v);
- the correlation's force on the particle, F_c = 3π μ d |U_s| F(φ, Re)/ε along U_s, is its whole
  force in a homogeneous bed (n F_c = −∇p);
- the missing part is supplied as an extra implicit rate κ_x of the particle's penalty, acting on the
  fluid share (1 − α) of its cells: the fluid there is dragged towards the particle's motion and the
  particle takes the momentum, so momentum stays conserved and the particle update stays implicit;
- κ_x is a controller, updated after every step from the drag the particle actually felt, F
  (resolved drag and the correction together): κ_x ← max(0, κ_x + ε (F_c − F·ŝ)/S), S the force per
  unit κ_x in its cells. The gain ε avoids counting twice: of an extra force on the fluid in a bed,
  the share 1 − ε comes back to the particles through the mean pressure gradient it raises (the
  resolved drag grows by (1 − ε)/ε of it), so a deficit ΔF needs ε ΔF more; with this gain a
  homogeneous bed settles in one step (any gain below 2ε converges).

Where the resolved drag already reaches the correlation's (an isolated sphere, whose filter average
sees its own wake slower than the stream; a dilute suspension at high Re, where the coarse mesh's
drag is too high) the correction adds nothing: κ_x stays 0. It never lowers a drag.
"""
from __future__ import annotations

import numpy as np
from mpi4py import MPI

from ..reference import beetstra_drag_factor, di_felice_drag_factor

CORRELATIONS = {"beetstra": beetstra_drag_factor, "di_felice": di_felice_drag_factor}
RATE_CAP = 1e3    # κ_x dt at most: the cells near the particle move with it to 1e-3


class FilterBins:
    """A lattice of filter bins over the domain's bounding box, each about ``width`` (m) wide, and
    the bin of each owned cell. Built once; ``averages`` is collective, ``at`` local."""

    def __init__(self, mesh, width: float):
        self.comm, self.mesh = mesh.comm, mesh
        self.lower = np.asarray(mesh.lower, float)
        span = np.asarray(mesh.upper, float) - self.lower
        self.counts = np.maximum(np.round(span / width).astype(np.int64), 1)
        self.size = span / self.counts
        n_owned = mesh.n_owned_cells
        index = np.clip(((mesh.cell_center[:n_owned] - self.lower) / self.size).astype(np.int64), 0, self.counts - 1)
        self.cell_bin = np.ravel_multi_index(index.T, self.counts)
        self.n_bins = int(np.prod(self.counts))

    def averages(self, u: np.ndarray, alpha: np.ndarray, solid_velocity: np.ndarray):
        """Collective. Per bin, the voidage ε (n_bins,) and the fluid's superficial velocity ε u_f
        (n_bins, 3): the mean of the cell velocities ``u`` (fluid and solid alike: the volume flux) less
        the solids' own, from the volume fractions ``alpha`` (n_owned,) and the particles' motion in each
        cell weighted by their shares, ``solid_velocity`` (n_owned, 3) = Σ α U. (Weighting the cell
        velocities by 1 − α instead misses the flow through the cut cells, a third of it in a packed bed
        at 3 cells per diameter.)"""
        n_owned = self.mesh.n_owned_cells
        volume = self.mesh.cell_volume[:n_owned]
        sums = np.zeros((5, self.n_bins))
        sums[0] = np.bincount(self.cell_bin, volume, minlength=self.n_bins)
        sums[1] = np.bincount(self.cell_bin, volume * np.minimum(alpha, 1.0), minlength=self.n_bins)
        for d in range(3):
            flux = volume * (u[:n_owned, d] - solid_velocity[:, d])
            sums[2 + d] = np.bincount(self.cell_bin, flux, minlength=self.n_bins)
        if self.comm.size > 1:
            self.comm.Allreduce(MPI.IN_PLACE, sums, op=MPI.SUM)
        total = np.maximum(sums[0], np.finfo(float).tiny)
        return 1.0 - sums[1] / total, (sums[2:] / total).T

    def at(self, x: np.ndarray, *fields: np.ndarray):
        """Local. Each per-bin field interpolated trilinearly between bin centres to the points ``x``
        (n, 3) (held constant beyond the outermost centres)."""
        t = (x - self.lower) / self.size - 0.5
        low = np.clip(np.floor(t).astype(np.int64), 0, np.maximum(self.counts - 2, 0))
        frac = np.clip(t - low, 0.0, 1.0) * (self.counts > 1)
        out = [np.zeros((len(x),) + f.shape[1:]) for f in fields]
        for corner in range(8):
            offset = np.array([(corner >> a) & 1 for a in range(3)])
            weight = np.prod(np.where(offset == 1, frac, 1.0 - frac), axis=1)
            index = np.ravel_multi_index((np.minimum(low + offset, self.counts - 1)).T, self.counts)
            for o, f in zip(out, fields):
                o += (weight if f.ndim == 1 else weight[:, None]) * f[index]
        return out


class DragCorrection:
    """The correction of one run (see the module docstring): its correlation, filter bins and the
    fluid's properties. Holds settings only; the rates κ_x per particle live in ``CouplingMemory``."""

    def __init__(self, mesh, correlation: str, width: float, fluid_density: float, viscosity: float):
        self.mesh, self.comm = mesh, mesh.comm
        self.factor = CORRELATIONS[correlation]
        self.bins = FilterBins(mesh, width)
        self.rho, self.mu = float(fluid_density), float(viscosity)

    def particle_bins(self, x: np.ndarray) -> np.ndarray:
        """(n,) the bin holding each centre (clamped to the lattice)."""
        index = np.clip(((x - self.bins.lower) / self.bins.size).astype(np.int64), 0, self.bins.counts - 1)
        return np.ravel_multi_index(index.T, self.bins.counts)

    def rates(self, state, memory) -> np.ndarray:
        """(n,) κ_x (1/s) of each particle: its bin's, from the last step (0 before the first)."""
        if memory.correction_rate is None:
            return np.zeros(len(state))
        return memory.correction_rate[self.particle_bins(state.x)]

    def slip(self, state, u: np.ndarray, alpha: np.ndarray, solid_velocity: np.ndarray, v: np.ndarray):
        """Collective. Each particle's local voidage ε (n,) and superficial slip U_s = ε (u_f − v) (n, 3),
        ``v`` (n, 3) its velocity (``FilterBins.averages`` for the rest); and each bin's voidage."""
        voidage, superficial = self.bins.averages(u, alpha, solid_velocity)
        eps, fluid = self.bins.at(state.x, voidage, superficial)
        eps = np.clip(eps, 0.3, 1.0)    # below a random close packing's voidage the bins are too coarse
        return eps, fluid - eps[:, None] * v, voidage

    def target(self, state, eps: np.ndarray, superficial: np.ndarray):
        """The correlation's force on each particle along its slip, (n,) N, and the slip's direction (n, 3)."""
        speed = np.linalg.norm(superficial, axis=1)
        d = 2.0 * state.radius
        reynolds = self.rho * speed * d / self.mu
        force = 3 * np.pi * self.mu * d * speed * self.factor(1.0 - eps, reynolds) / eps
        direction = superficial / np.maximum(speed, np.finfo(float).tiny)[:, None]
        return force, direction

    def update(self, state, rate: np.ndarray, voidage: np.ndarray, target: np.ndarray, direction: np.ndarray,
               force: np.ndarray, sensitivity: np.ndarray, dt: float) -> np.ndarray:
        """(n_bins,) κ_x of each bin for the next step (``rate``: this step's): raised by
        ε (Σ F_c − Σ F·ŝ)/Σ S where the drag the bin's particles felt, ``force`` (n, 3) along their slips
        ``direction`` (n, 3), falls short of their correlation's ``target`` (n,), lowered where it
        exceeds it, never below 0. ``sensitivity`` S (n,): a particle's force along ŝ per unit κ_x
        (N s); ``voidage`` (n_bins,). The bin's mean drag is the correlation's (what a bed's pressure
        drop measures); how it is shared among the particles, by their own flow, is resolved."""
        n_bins = self.bins.n_bins
        where = self.particle_bins(state.x)
        felt = np.einsum("ij,ij->i", force, direction)
        deficit = np.bincount(where, target - felt, minlength=n_bins)
        response = np.bincount(where, sensitivity, minlength=n_bins)
        scale = np.bincount(where, target, minlength=n_bins)
        usable = response > 1e-12 * np.maximum(scale, np.finfo(float).tiny)
        step = np.where(usable, voidage * deficit / np.where(usable, response, 1.0), 0.0)
        return np.clip(rate + step, 0.0, RATE_CAP / dt)
