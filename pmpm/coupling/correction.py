"""A drag correction for under-resolved particles (``[coupling] drag_correction``, default off).

On a few cells per diameter the flow through the gaps between particles is not resolved: a packed
bed's pores are about a cell wide, and its pressure drop comes out too low (at 3 cells per diameter
0.42 of Ergun's at Re 1, 0.53 at Re 10, 0.83 at Re 100; docs/coupling.md, "Dense suspensions").
The correction brings the particles' drag up to a correlation for spheres among spheres at the
local voidage (Di Felice 1994, or Beetstra, van der Hoef & Kuipers 2007), adding only what the
resolved drag lacks:

- the local voidage ε and the fluid's superficial velocity are averages over a box about
  ``correction_filter`` wide (default 3 diameters) around each particle: 3 × 3 × 3 bins of a
  lattice at a third of that width, centred on the bin holding the centre (``FilterBins``); the
  slip is U_s = ε u_f − ε v;
- the correlation's force on the particle, F_c = 3π μ d |U_s| F(φ, Re)/ε along U_s, is its whole
  force in a homogeneous bed (n F_c = −∇p);
- the missing part is supplied as an extra implicit rate κ_x of the penalty, acting on the fluid
  share (1 − α) of the particle's cells: the fluid there is dragged towards the particle's motion
  and the particle takes the momentum, so momentum stays conserved and the particle update stays
  implicit;
- κ_x is a controller, one value per pool (a block of the coarse lattice, the filter's width),
  updated after every step from the drag the pool's particles felt, F (resolved drag and the
  correction together): κ_x ← max(0, κ_x + g ε̄ (Σ F_c − Σ F·ŝ)/Σ S), S the force per unit κ_x in
  their cells. ε̄ avoids counting twice (of an extra force on the fluid in a bed, the share 1 − ε
  comes back to the particles through the mean pressure gradient it raises); g = ``GAIN`` = 0.1,
  since the force felt in the step after a change of κ_x responds more than S foresees (the fluid
  in the cells has not slowed yet): with g = 1 and 0.5 the rate swung between 0 and its cap from
  step to step; with 0.1 a packed bed settles within about 30 steps.

Where the resolved drag exceeds the correlation's because the mesh is too coarse for the particle's
boundary layer (≈ d/√Re, thinner than a cell above Re = (d/h)²: the drag comes out too high,
docs/coupling.md), κ_x falls to 0 and a *relief* takes over: each such particle is pushed against
its slip by β w F_c (F_c its correlation's force at the end of the last step), and the same force
is put into the fluid around it, in the cells outside every particle's control volume, as an
explicit source of the momentum equations; momentum stays conserved. w = clip(Re/(d/h)² − 1, 0, 1)
(``relievable``) limits it to those particles: below (d/h)² a lone sphere's resolved drag is right,
and its filtered slip, slowed by its own disturbance across the filter box, is not the stream's (at
Re 0.1 a relief took 20 % off a drag that was within 3 %). β is the pool's, from the same
controller over the relievable particles: β ← clip(β − g ε̄ Σ w (F_c − F·ŝ)/Σ w F_c, 0,
``RELIEF_CAP``). The relief lags the slip by a step and offsets only the excess of the resolved
drag (β w F_c < F), so the resolved drag's implicit hold on the particle still dominates.
"""
from __future__ import annotations

import numpy as np
from mpi4py import MPI

from ..reference import beetstra_drag_factor, di_felice_drag_factor, di_felice_standard_drag_factor
from .memory import by_id

CORRELATIONS = {"beetstra": beetstra_drag_factor, "di_felice": di_felice_drag_factor,
                "di_felice_standard": di_felice_standard_drag_factor}
RATE_CAP = 1e3    # κ_x dt at most: the cells near the particle move with it to 1e-3
GAIN = 0.1        # of the one-step gain ε: the force felt responds to κ_x more than S foresees
RELIEF_CAP = 2.0  # β at most: the coarsest mesh's drag at Re 1000 is about twice the correlation's


class FilterBins:
    """A lattice of bins about ``width``/3 wide over the domain's bounding box, the bin of each owned
    cell, and blocks of 3 × 3 × 3 bins. A particle's filtered voidage and fluid flux are those of
    the block centred on the bin that holds its centre (a box about ``width`` wide, so the box moves
    with the particle in steps of a bin); the drag controller pools the particles of each block of
    the coarse lattice (every third bin along each axis). Built once; ``block_averages`` is
    collective, the rest local."""

    def __init__(self, mesh, width: float):
        self.comm, self.mesh = mesh.comm, mesh
        self.lower = np.asarray(mesh.lower, float)
        span = np.asarray(mesh.upper, float) - self.lower
        self.counts = np.maximum(np.round(3.0 * span / width).astype(np.int64), 1)
        self.size = span / self.counts
        self.n_bins = int(np.prod(self.counts))
        self.pool_counts = -(-self.counts // 3)
        self.n_pools = int(np.prod(self.pool_counts))
        self.cell_bin = np.ravel_multi_index(self.index(mesh.cell_center[:mesh.n_owned_cells]).T, self.counts)

    def index(self, x: np.ndarray) -> np.ndarray:
        """(n, 3) the lattice index of the bin holding each point (clamped to the lattice)."""
        return np.clip(((x - self.lower) / self.size).astype(np.int64), 0, self.counts - 1)

    def bin_of(self, x: np.ndarray) -> np.ndarray:
        """(n,) the bin holding each point."""
        return np.ravel_multi_index(self.index(x).T, self.counts)

    def pool_of(self, x: np.ndarray) -> np.ndarray:
        """(n,) the controller's pool (a block of the coarse lattice) holding each point."""
        return np.ravel_multi_index((self.index(x) // 3).T, self.pool_counts)

    def block_averages(self, u: np.ndarray, alpha: np.ndarray, solid_velocity: np.ndarray):
        """Collective. Per bin, over the 3 × 3 × 3 bins around it: the voidage ε (n_bins,) and the
        fluid's superficial velocity ε u_f (n_bins, 3), the mean of the cell velocities ``u`` (fluid
        and solid alike: the volume flux) less the solids' own, from the volume fractions ``alpha``
        (n_owned,) and the particles' motion in each cell weighted by their shares,
        ``solid_velocity`` (n_owned, 3) = Σ α U. (Weighting the cell velocities by 1 − α instead
        misses the flow through the cut cells, a third of it in a packed bed at 3 cells per
        diameter.)"""
        n_owned = self.mesh.n_owned_cells
        volume = self.mesh.cell_volume[:n_owned]
        sums = np.zeros((5, self.n_bins))
        sums[0] = np.bincount(self.cell_bin, volume, minlength=self.n_bins)
        sums[1] = np.bincount(self.cell_bin, volume * np.minimum(alpha, 1.0), minlength=self.n_bins)
        for d in range(3):
            sums[2 + d] = np.bincount(self.cell_bin, volume * (u[:n_owned, d] - solid_velocity[:, d]),
                                      minlength=self.n_bins)
        if self.comm.size > 1:
            self.comm.Allreduce(MPI.IN_PLACE, sums, op=MPI.SUM)
        nx, ny, nz = self.counts
        padded = np.pad(sums.reshape(5, nx, ny, nz), ((0, 0), (1, 1), (1, 1), (1, 1)))
        block = np.zeros((5, nx, ny, nz))
        for i in range(3):          # 27 shifted views: the block sums without a loop over bins
            for j in range(3):
                for k in range(3):
                    block += padded[:, i:i + nx, j:j + ny, k:k + nz]
        block = block.reshape(5, -1)
        total = np.maximum(block[0], np.finfo(float).tiny)
        return 1.0 - block[1] / total, (block[2:] / total).T


class DragCorrection:
    """The correction of one run (see the module docstring): its correlation, filter bins and the
    fluid's properties. Holds settings only; the rates κ_x per particle live in ``CouplingMemory``."""

    def __init__(self, mesh, correlation: str, width: float, fluid_density: float, viscosity: float):
        self.mesh, self.comm = mesh, mesh.comm
        self.factor = CORRELATIONS[correlation]
        self.bins = FilterBins(mesh, width)
        self.rho, self.mu = float(fluid_density), float(viscosity)

    def rates(self, state, memory) -> np.ndarray:
        """(n,) κ_x (1/s) of each particle: its pool's, from the last step (0 before the first)."""
        if memory.correction_rate is None:
            return np.zeros(len(state))
        return memory.correction_rate[self.bins.pool_of(state.x)]

    def relief(self, state, memory) -> np.ndarray | None:
        """(n, 3) the relief force on each particle (N): −β F_c, its pool's β and its correlation's
        force at the end of the last step (0 for a particle new to the flow); None where no pool relieves."""
        if memory.correction_relief is None or not memory.correction_relief.any():
            return None
        position, same = by_id(memory.under_id, state.id)
        beta = memory.correction_relief[self.bins.pool_of(state.x)]
        return np.where(same[:, None], -beta[:, None] * memory.under_target[position], 0.0)

    def slip(self, state, u: np.ndarray, alpha: np.ndarray, solid_velocity: np.ndarray, v: np.ndarray):
        """Collective. Each particle's local voidage ε (n,) and superficial slip U_s = ε (u_f − v) (n, 3),
        ``v`` (n, 3) its velocity (``FilterBins.block_averages`` for the rest)."""
        voidage, superficial = self.bins.block_averages(u, alpha, solid_velocity)
        where = self.bins.bin_of(state.x)
        eps = np.clip(voidage[where], 0.3, 1.0)    # below a random close packing's voidage the filter is too coarse
        return eps, superficial[where] - eps[:, None] * v

    def target(self, state, eps: np.ndarray, superficial: np.ndarray, h: np.ndarray):
        """The correlation's force on each particle along its slip, (n,) N, the slip's direction
        (n, 3), and how far the relief may act on it (n,), w = clip(Re/(d/h)² − 1, 0, 1), ``h`` (n,)
        the size of its cells (m)."""
        speed = np.linalg.norm(superficial, axis=1)
        d = 2.0 * state.radius
        reynolds = self.rho * speed * d / self.mu
        force = 3 * np.pi * self.mu * d * speed * self.factor(1.0 - eps, reynolds) / eps
        direction = superficial / np.maximum(speed, np.finfo(float).tiny)[:, None]
        relievable = np.clip(reynolds * (h / d) ** 2 - 1.0, 0.0, 1.0)
        return force, direction, relievable

    def update(self, state, rate: np.ndarray, relief: np.ndarray, eps: np.ndarray, target: np.ndarray,
               direction: np.ndarray, relievable: np.ndarray, force: np.ndarray, sensitivity: np.ndarray, dt: float,
               holders):
        """(κ_x, β), each (n_pools,), of each pool for the next step (``rate``, ``relief``: this step's).
        D = Σ F_c − Σ F·ŝ, where the drag the pool's particles felt, ``force`` (n, 3) along their slips
        ``direction`` (n, 3), falls short of their correlation's ``target`` (n,) (D > 0) or exceeds it:
        κ_x moves by g ε̄ D/Σ S, never below 0; once it is 0, β moves by −g ε̄ D_w/Σ w F_c, never below
        0, D_w = Σ w (F_c − F·ŝ) over the particles weighted by ``relievable`` w (n,).
        ``sensitivity`` S (n,): a particle's force along ŝ per unit κ_x (N s); ``eps`` (n,) each
        particle's filtered voidage, ε̄ their mean in the pool; g = ``GAIN``. The pool's mean drag is
        the correlation's (what a bed's pressure drop measures); how it is shared among the
        particles, by their own flow, is resolved. ``holders`` (``holders.Holders``): the pools' sums
        are taken over the particles this rank owns, then over the ranks."""
        n_bins = self.bins.n_pools
        mine = holders.owned
        where = self.bins.pool_of(state.x[mine])
        felt = np.einsum("ij,ij->i", force[mine], direction[mine])
        target, relievable = target[mine], relievable[mine]
        sums = holders.across_ranks(np.stack([np.bincount(where, values, minlength=n_bins) for values in (
            np.ones(len(where)), eps[mine], target - felt, sensitivity[mine], target, relievable * (target - felt),
            relievable * target)]).astype(float))   # (bincount of nothing is int)
        count, voidage_sum, deficit, response, scale, excess, relieved = sums
        voidage = voidage_sum / np.maximum(count, 1)
        tiny = np.finfo(float).tiny
        usable = response > 1e-12 * np.maximum(scale, tiny)
        step = np.where(usable, GAIN * voidage * deficit / np.where(usable, response, 1.0), 0.0)
        relieving = (rate <= 0.0) & ((relief > 0.0) | (excess < 0.0)) & (relieved > 0.0)
        new_relief = np.where(relieving, relief - GAIN * voidage * excess / np.maximum(relieved, tiny), relief)
        new_rate = np.where(relieving, rate, rate + step)
        return np.clip(new_rate, 0.0, RATE_CAP / dt), np.clip(new_relief, 0.0, RELIEF_CAP)
