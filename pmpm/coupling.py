"""Big particles in the flow: touched cells, volume fractions, velocity patching, drag and torque.

The paper's eq. 1–2 (Figure 1): a cell is *touched* by a particle when one of its vertices lies in
the sphere; in touched cells the fluid velocity becomes (1 − α) u + α (V + ω × r), and the
momentum that this patch adds to the fluid is taken from the particle: that is the drag and the
torque (r × F, r from the particle centre to the cell centre).

Where the patch happens. The flow solver calls :meth:`Coupling.exchange` between its momentum
predictor and its projection (direct forcing, as in immersed-boundary methods, ``forcing_passes``
times), so the divergence-free face fluxes honour the particles; then once more after the
projection (the paper's patch), where the particles are updated with all the momentum exchanged.

The particle update, and why it is implicit. With M the fluid mass a particle covers
(ρ_f Σ α V_cell) and ū* the mass-weighted predicted fluid velocity under it, the momentum that the
patch exchanges is M (ū* − Vⁿ), so the paper's explicit update is

    m (Vⁿ⁺¹ − Vⁿ) = dt F_ext + M (ū* − Vⁿ),

which amplifies a velocity error by (M − m)/m each step: it oscillates and grows once
ρ_p/ρ_f < 1/2, and rings well before that. pmpm solves particle and covered fluid together,

    (m + (1 − θ) M) (Vⁿ⁺¹ − Vⁿ) = dt F_ext + M (ū* − Vⁿ),     θ = min(1, m/M),

(the same for ω with the moments of inertia), which moves V at most all the way to ū*, never past
it (docs/coupling.md has the measured stability map). Where m ≥ M (ρ_p ≥ ρ_f with M ≈ ρ_f V) it is
the paper's update exactly; for lighter particles it adds M − m to the particle's inertia, an
error in transients only (terminal velocities are unchanged). ``[coupling] update = "explicit"`` keeps θ = 1 always, and
the run stops (exit 3) when a particle's velocity starts to ring.

Volume fraction rules (``[coupling] volume_fraction``): ``nodes`` (the paper: the share of the
cell's vertices inside), ``subcell`` (the share of k³ sample points of the cell inside).

Parallel: each rank sums over its owned cells only; the per-particle sums meet in one Allreduce,
then every rank applies the same update to its replicated copy of the particles.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse
from mpi4py import MPI
from scipy.spatial import cKDTree

from .errors import NumericalError
from .particles import ParticleState


class Touched:
    """(particle, owned cell, α) triples of one step, on this rank."""

    def __init__(self, particle, cell, alpha):
        self.particle, self.cell, self.alpha = particle, cell, alpha


class Coupling:
    """Collective. Particle–fluid coupling on one mesh.

    Parameters
    ----------
    mesh : pmpm.mesh.Mesh
    section : the case's [coupling] section (mode, volume_fraction, subcell_points, update)
    fluid_density : ρ_f (kg/m³)
    """

    def __init__(self, mesh, section, fluid_density: float):
        self.mesh, self.comm = mesh, mesh.comm
        self.rho = float(fluid_density)
        self.two_way = section.mode == "two-way"
        self.rule = section.volume_fraction
        self.k = int(section.subcell_points)
        self.explicit = section.update == "explicit"
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
        self.samples = reference_samples(mesh.cell_type, self.k) if self.rule == "subcell" else None
        self.pending = None           # momentum exchanged by the earlier forcing passes of this step
        self.last_change = None       # for detecting a ringing explicit update
        self.ringing = None

    # -- 1. locate ------------------------------------------------------------------------------
    def locate(self, state: ParticleState) -> Touched:
        """Local. The owned cells each particle touches, with its volume fraction α in each."""
        reach = state.radius + (self.cell_diameter if self.rule == "subcell" else 0.0)
        near = np.all((state.x + reach[:, None] >= self.lower) & (state.x - reach[:, None] <= self.upper), axis=1)
        candidates = np.flatnonzero(near)
        empty = Touched(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
        if len(candidates) == 0:
            return empty
        hits = self.tree.query_ball_point(state.x[candidates], reach[candidates])
        counts = np.fromiter((len(h) for h in hits), np.int64, len(hits))
        if counts.sum() == 0:
            return empty
        rows = np.repeat(np.arange(len(candidates)), counts)
        columns = np.concatenate([np.asarray(h, np.int64) for h in hits if len(h)])
        inside = scipy.sparse.csr_matrix((np.ones(len(rows)), (rows, columns)),
                                         shape=(len(candidates), self.tree.n))
        per_cell = (inside @ self.incidence).tocoo()       # vertices inside, per (particle, cell)
        particle = candidates[per_cell.row]
        cell = per_cell.col.astype(np.int64)
        if self.rule == "nodes":
            alpha = per_cell.data / self.vertices_per_cell
        else:
            alpha = self.sampled_fraction(state, particle, cell)
            keep = alpha > 0
            particle, cell, alpha = particle[keep], cell[keep], alpha[keep]
        return Touched(particle, cell, alpha)

    def sampled_fraction(self, state, particle, cell) -> np.ndarray:
        """Share of the cell's k³ sample points inside the sphere, per (particle, cell) pair."""
        corners = self.mesh.vertex_xyz[self.mesh.cell_vertices[cell]]            # (m, nv, 3)
        gap = corners - state.x[particle, None, :]
        vertex_inside = np.einsum("mvd,mvd->mv", gap, gap) <= state.radius[particle, None] ** 2
        # a convex cell with every vertex inside the (convex) sphere lies inside it: α = 1, no sampling
        alpha = vertex_inside.all(axis=1).astype(float)
        cut = np.flatnonzero(alpha < 1)
        chunk = max(1, 2_000_000 // max(1, len(self.samples)))
        for start in range(0, len(cut), chunk):
            part = cut[start:start + chunk]
            points = np.einsum("sv,mvd->msd", self.samples, corners[part])     # (m, k³, 3)
            gap = points - state.x[particle[part], None, :]
            inside = np.einsum("msd,msd->ms", gap, gap) <= state.radius[particle[part], None] ** 2
            alpha[part] = inside.mean(axis=1)
        return alpha

    def shared_alpha(self, touched: Touched) -> np.ndarray:
        """α of each (particle, cell) pair, scaled down where overlapping particles cover a cell
        more than once, so that a cell is never patched beyond its own volume."""
        total = np.bincount(touched.cell, touched.alpha, minlength=self.mesh.n_owned_cells)
        return touched.alpha / np.maximum(total[touched.cell], 1.0)

    def volume_fraction(self, touched: Touched) -> np.ndarray:
        """(n_owned,) particle volume fraction per owned cell, at most 1."""
        total = np.bincount(touched.cell, touched.alpha, minlength=self.mesh.n_owned_cells)
        return np.minimum(total, 1.0)

    # -- 2. exchange: drag, torque, the particle update and the patch ---------------------------
    def exchange(self, state: ParticleState, touched: Touched, u: np.ndarray, dt: float,
                 external_force: np.ndarray, external_torque: np.ndarray, last: bool = True,
                 step: int = 0, time: float = 0.0):
        """Collective. Momentum exchange of one flow step (or one forcing pass of it).

        Sums, over ranks, the fluid mass each particle covers and its momentum deviation from the
        particle's rigid motion as the last pass patched it. Every pass (multi-direct forcing,
        ``pmpm.fluid``) solves the particle update (module docstring) with the momentum of all
        passes so far and, in two-way mode, patches the updated rigid motion into the owned rows
        of ``u``; the last pass returns the forces. (With ``update = "explicit"`` the passes before
        the last patch the step's first motion, as the paper's single patch does.)

        Returns
        -------
        force, torque : (n, 3) hydrodynamic force (N) and torque (N m) on each particle, such that
            m (Vⁿ⁺¹ − Vⁿ) = dt (force + external_force) for free particles; None before the last pass.
        """
        n = len(state)
        mesh = self.mesh
        p, c = touched.particle, touched.cell
        alpha = self.shared_alpha(touched)
        r = mesh.cell_center[c] - state.x[p]
        mass = self.rho * alpha * mesh.cell_volume[c]
        # the velocities patched by the last pass (this step's start for the first): the deviation
        # from them is the momentum this pass exchanges
        if self.pending is None or len(self.pending) != n:
            self.pending = np.zeros((n, 6))
            self.patched_v, self.patched_omega = state.v, state.omega
        rigid = self.patched_v[p] + np.cross(self.patched_omega[p], r)
        deviation = mass[:, None] * (u[c] - rigid)
        sums = np.zeros((n, 8))
        sums[:, 0] = np.bincount(p, mass, minlength=n)
        for d in range(3):
            sums[:, 1 + d] = np.bincount(p, deviation[:, d], minlength=n)
        spin = np.cross(r, deviation)
        for d in range(3):
            sums[:, 4 + d] = np.bincount(p, spin[:, d], minlength=n)
        sums[:, 7] = np.bincount(p, mass * (2.0 / 3.0) * np.einsum("ij,ij->i", r, r), minlength=n)
        if self.comm.size > 1:
            self.comm.Allreduce(MPI.IN_PLACE, sums, op=MPI.SUM)
        self.pending += sums[:, 1:7]
        covered, moment = sums[:, 0], sums[:, 7]
        momentum, angular = self.pending[:, :3], self.pending[:, 3:]

        # the particle update from all the momentum exchanged so far, every pass: the next pass then
        # patches the updated motion, so the passes converge on particle and fluid together (patching
        # the step's first velocity every pass made light particles ring on coarse meshes)
        free = state.movable
        m, inertia = state.mass, state.inertia
        # θ = min(1, m/M): the covered fluid mass M, not ρf V, decides (on a coarse mesh M can be
        # several times the sphere's own volume of fluid); likewise for the moments of inertia
        tiny = np.finfo(float).tiny
        theta = np.ones(n) if self.explicit else np.minimum(1.0, m / np.maximum(covered, tiny))
        theta_spin = np.ones(n) if self.explicit else np.minimum(1.0, inertia / np.maximum(moment, tiny))
        dv = (dt * external_force + momentum) / (m + (1 - theta) * covered)[:, None]
        dw = (dt * external_torque + angular) / (inertia + (1 - theta_spin) * moment)[:, None]
        new_v = np.where(free[:, None], state.v + dv, state.v)
        new_omega = np.where(free[:, None], state.omega + dw, state.omega)
        if self.explicit and not last:   # the paper's update: every pass patches the step's first motion
            new_v, new_omega = self.patched_v, self.patched_omega
        if self.two_way:
            self.patch(u, c, alpha, new_v[p] + np.cross(new_omega[p], r))
        if not last:
            self.patched_v, self.patched_omega = new_v, new_omega
            return None
        self.pending = None
        force = np.where(free[:, None], m[:, None] * dv / dt - external_force, momentum / dt)
        torque = np.where(free[:, None], inertia[:, None] * dw / dt - external_torque, angular / dt)
        if self.explicit:
            self.watch_ringing(state, np.where(free[:, None], dv, 0.0), step, time)
        return force, torque

    def carry_fluid(self, state: ParticleState, touched: Touched, u: np.ndarray, fresh: np.ndarray) -> None:
        """Local (owned rows of ``u``). Particles new to the flow (present at the start, or just
        injected): the fluid they cover is the solver's, not the user's, so it starts moving with
        them. Otherwise a particle released at speed into still fluid would spend its first step
        accelerating its own volume of fluid (a ρp/ρf = 2 sphere lost half its momentum so)."""
        if not self.two_way:
            return
        pick = fresh[touched.particle]
        p, c, alpha = touched.particle[pick], touched.cell[pick], self.shared_alpha(touched)[pick]
        rigid = state.v[p] + np.cross(state.omega[p], self.mesh.cell_center[c] - state.x[p])
        self.patch(u, c, alpha, rigid)

    def patch(self, u, cell, alpha, target):
        """u ← (1 − α) u + α target in the touched owned cells (eq. 1's velocity patch)."""
        change = alpha[:, None] * (target - u[cell])
        n_owned = self.mesh.n_owned_cells
        for d in range(3):
            u[:n_owned, d] += np.bincount(cell, change[:, d], minlength=n_owned)

    def watch_ringing(self, state, change, step, time):
        """Stop an explicit update whose velocity changes flip sign and grow (the light-particle instability)."""
        n = len(state)
        if self.last_change is None or len(self.last_change) != n:
            self.last_change, self.ringing = change, np.zeros(n, np.int64)
            return
        size, before = np.linalg.norm(change, axis=1), np.linalg.norm(self.last_change, axis=1)
        flips = np.einsum("ij,ij->i", change, self.last_change) < 0
        growing = flips & (size > 1.5 * before) & (size > 1e-9)
        self.ringing = np.where(growing, self.ringing + 1, 0)
        self.last_change = change
        if (self.ringing >= 4).any():
            i = int(np.argmax(self.ringing))
            raise NumericalError(
                f"step {step}, t = {time:.6g} s: particle {state.id[i]} (density ratio "
                f"{state.density[i] / self.rho:.3g}) rings: its velocity change flips sign and grows every "
                "step, the explicit coupling instability of light particles; use [coupling] update = "
                "\"implicit\" (the default), or a smaller [run] dt")


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
