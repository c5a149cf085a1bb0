"""Big particles in the flow: touched cells, volume fractions, the forcing, drag and torque.

The paper's eq. 1–2 (Figure 1): a cell is *touched* by a particle when one of its vertices lies in
the sphere, and carries the particle's volume fraction α; the fluid there is driven towards the
rigid motion U = V + ω × r, and the momentum this takes from the particle is the drag and the
torque (r × F, r from the particle centre to the cell centre). Two forcings (``[coupling] forcing``):

``penalty`` (default). A penalty κ (U − u) with κ = s α/(1 − α) ν/h² (``penalty_strength`` s, the
solid's friction) plus a blockage rate (1000/6) α⁸ U_rel/h that beats convection in the cells a
particle fills (:meth:`Coupling.penalty_rates`), solved implicitly with the diffusion of the momentum
predictor (the flow solver calls :meth:`Coupling.penalty_terms` before each of its ``forcing_passes``
momentum solves, and damps its pressure terms in penalized cells by 1/(1 + κ dt)). In a cut cell the
friction balances the fluid's own viscous exchange, a balance without dt in it, so the forces hardly
depend on the time step. The impulse on a particle is what the penalty took, J = Σ ρ V κ dt (u − U)
at the projected u, plus the change of the momentum of the fluid under it over a control volume
moving with it (:meth:`Coupling.begin_step`); each pass updates the particles' guess of their new
motion, damped by the cells' own response so that light particles converge
(:meth:`Coupling.penalty_exchange`).

``patch`` (the paper). After each momentum solve, u ← (1 − α) u + α U in touched cells, and once
more after the projection; the momentum the patch adds is taken from the particle, with the update

    (m + (1 − θ) M) (Vⁿ⁺¹ − Vⁿ) = dt F_ext + M (ū* − Vⁿ),     θ = min(1, m/M),

M the covered fluid mass and ū* the predicted fluid velocity under the particle (θ = 1 is the
paper's explicit update, which rings for light particles). Re-blending the cut cells every step
makes its forces depend on ν dt/h².

``[coupling] update = "explicit"`` takes the impulse as it comes (no guesses, no damping), and the
run stops (exit 3) when a particle's velocity starts to ring. Volume fraction rules
(``[coupling] volume_fraction``): ``nodes`` (the paper: the share of the cell's vertices inside),
``subcell`` (the share of k³ sample points of the cell inside). docs/coupling.md has the
measurements.

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
    viscosity : μ (Pa s)
    """

    def __init__(self, mesh, section, fluid_density: float, viscosity: float):
        self.mesh, self.comm = mesh, mesh.comm
        self.rho = float(fluid_density)
        self.two_way = section.mode == "two-way"
        self.rule = section.volume_fraction
        self.k = int(section.subcell_points)
        self.explicit = section.update == "explicit"
        self.penalty = section.forcing == "penalty"
        self.penalty_strength = float(section.penalty_strength)
        self.nu = float(viscosity) / self.rho
        self.h2 = mesh.cell_volume[:mesh.n_owned_cells] ** (2 / 3)
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
        self.internal_end = None      # (ids, fluid momentum under each particle, centres) at the last step's end
        self.pending = None           # momentum exchanged by the earlier forcing passes of this step
        self.last_change = None       # for detecting a ringing explicit update
        self.ringing = None

    # -- 1. locate ------------------------------------------------------------------------------
    def locate(self, state: ParticleState) -> Touched:
        """Local. The owned cells each particle touches, with its volume fraction α in each."""
        # the penalty also needs the cells near the surface that hold no vertex or sample point
        # inside: its smooth fractions (``smooth_fraction``) reach them
        extended = self.rule == "subcell" or self.penalty
        reach = state.radius + (self.cell_diameter if extended else 0.0)
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
        if not extended:
            return Touched(particle, cell, per_cell.data / self.vertices_per_cell)
        if self.rule == "nodes":
            alpha = self.vertex_fraction(state, particle, cell)
        else:
            alpha = self.sampled_fraction(state, particle, cell)
        keep = alpha > 0
        if self.penalty:
            keep |= self.smooth_fraction(state, Touched(particle, cell, alpha), shared=False) > 0
        return Touched(particle[keep], cell[keep], alpha[keep])

    def vertex_fraction(self, state, particle, cell) -> np.ndarray:
        """The paper's α: the share of the cell's vertices inside the sphere, per (particle, cell) pair."""
        gap = self.mesh.vertex_xyz[self.mesh.cell_vertices[cell]] - state.x[particle, None, :]
        return (np.einsum("mvd,mvd->mv", gap, gap) <= state.radius[particle, None] ** 2).mean(axis=1)

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

    def alpha_per_cell(self, touched: Touched) -> np.ndarray:
        """(n_owned,) Σ α over the particles touching each owned cell (may exceed 1 where they overlap)."""
        return np.bincount(touched.cell, touched.alpha, minlength=self.mesh.n_owned_cells)

    def shared_alpha(self, touched: Touched) -> np.ndarray:
        """α of each (particle, cell) pair, scaled down where overlapping particles cover a cell
        more than once, so that a cell is never patched beyond its own volume."""
        total = self.alpha_per_cell(touched)
        return touched.alpha / np.maximum(total[touched.cell], 1.0)

    def volume_fraction(self, touched: Touched) -> np.ndarray:
        """(n_owned,) particle volume fraction per owned cell, at most 1."""
        return np.minimum(self.alpha_per_cell(touched), 1.0)

    # -- 2a. the penalty (the default forcing) ------------------------------------------------
    def penalty_rates(self, touched: Touched, speed: np.ndarray) -> np.ndarray:
        """κ (1/s) of each (particle, cell) pair, from the cell's total volume fraction α, shared among
        the particles in it by their α:

            κ = min(s α/(1 − α), 1000) ν/h²  +  (1000/6) α⁸ |u − U|_max / h.

        The first term is the solid's viscous friction on the fluid in the cell (s = ``penalty_strength``,
        fitted on the Stokes drag): it sets where the particle's surface lies, without dt. The second
        is the blockage: a cell the particle fills must stop the flow that the pressure drives through
        it, ∇p/ρ ~ |u − U|²/d, faster than convection brings it; ``speed`` |u − U|_max is the particle's
        (``relative_speed``). A cell wholly inside gets 167 times either exchange rate with its
        neighbours (6 ν/h² by diffusion, |u − U|/h by convection); α⁸ leaves the friction of the cut
        cells viscous, so the surface stays where the Stokes fit put it (docs/coupling.md)."""
        total = self.alpha_per_cell(touched)[touched.cell]
        covered = np.minimum(total, 1.0)
        friction = np.minimum(self.penalty_strength * covered / np.maximum(1.0 - covered, 1e-300), PENALTY_CAP)
        h2 = self.h2[touched.cell]
        blockage = PENALTY_CAP / 6.0 * covered ** 8 * speed[touched.particle] / np.sqrt(h2)
        return (friction * self.nu / h2 + blockage) * touched.alpha / np.maximum(total, 1e-300)

    def relative_speed(self, state: ParticleState, touched: Touched, u: np.ndarray) -> np.ndarray:
        """Collective. (n,) the largest |u − U| (m/s) over each particle's touched cells at the step's
        start, U its rigid motion: the speed at which the flow meets it, for the penalty's blockage."""
        p, c = touched.particle, touched.cell
        rigid = state.v[p] + np.cross(state.omega[p], self.mesh.cell_center[c] - state.x[p])
        slip = np.linalg.norm(u[c] - rigid, axis=1)
        order = np.lexsort((slip, p))                     # by particle, then slip: each group's last is its max
        last = np.append(p[order][1:] != p[order][:-1], True) if len(p) else np.zeros(0, bool)
        speed = np.zeros(len(state))
        speed[p[order][last]] = slip[order][last]
        if self.comm.size > 1:
            self.comm.Allreduce(MPI.IN_PLACE, speed, op=MPI.MAX)
        return speed

    def penalty_terms(self, state: ParticleState, touched: Touched):
        """Local. (V κ, V κ U) per owned cell for the next momentum solve, U the rigid motion of the
        current guess of the particles' new velocities (zero in one-way mode: the fluid is not forced)."""
        n_owned = self.mesh.n_owned_cells
        diagonal, target = np.zeros(n_owned), np.zeros((n_owned, 3))
        if not self.two_way or len(touched.cell) == 0:
            return diagonal, target
        p, c = touched.particle, touched.cell
        weight = self.mesh.cell_volume[c] * self.kappa            # (begin_step)
        rigid = self.patched_v[p] + np.cross(self.patched_omega[p], self.mesh.cell_center[c] - state.x[p])
        diagonal += np.bincount(c, weight, minlength=n_owned)
        for d in range(3):
            target[:, d] = np.bincount(c, weight * rigid[:, d], minlength=n_owned)
        return diagonal, target

    def start_passes(self, state: ParticleState) -> None:
        """The first pass of a step starts from the particles' velocities at the step's start."""
        if self.pending is None or len(self.pending) != len(state):
            self.pending = np.zeros((len(state), 6))
            self.patched_v, self.patched_omega = state.v, state.omega

    def begin_step(self, state: ParticleState, touched: Touched, u: np.ndarray) -> None:
        """Collective (penalty forcing). The momentum of the fluid under each particle at the step's
        start, against which the step's change ΔP is measured (``penalty_exchange``).

        The fluid inside a moving particle is a control volume that moves with it, so its momentum
        change includes what the particle's advance covered and uncovered (Reynolds transport):
        the start is the fluid under the particle *as the last step left it*. Measured over a fixed
        set of cells instead, the fluid a moving sphere sweeps up ahead (slower than the sphere) and
        leaves behind (at its speed) gave it a thrust: at Re = 8 a sphere moving through still fluid
        felt 9 % less drag than the same sphere held in a stream. "Under" weighs each cell by a
        smooth fraction (``smooth_fraction``), not α: the sampled α jumps as sample points cross the
        surface, and those jumps times the fluid's momentum made light particles ring."""
        self.pending = None
        self.start_passes(state)
        if not self.penalty:
            return
        # the particles stay put during the flow step: their rates and smooth fractions hold for every pass
        self.kappa = self.penalty_rates(touched, self.relative_speed(state, touched, u))
        self.under_mass = self.rho * self.smooth_fraction(state, touched) * self.mesh.cell_volume[touched.cell]
        self.internal_start = self.fluid_under(state, touched, u, self.under_mass)   # particles new to the flow
        if self.internal_end is not None:
            known_ids, known, centre = self.internal_end
            position = np.minimum(np.searchsorted(known_ids, state.id), max(len(known_ids) - 1, 0))
            same = (known_ids[position] == state.id) if len(known_ids) else np.zeros(len(state), bool)
            start = known[position[same]].copy()
            # its moment about where the centre is now: L' = L − (x' − x) × P
            start[:, 3:] -= np.cross(state.x[same] - centre[position[same]], start[:, :3])
            self.internal_start[same] = start

    def smooth_fraction(self, state: ParticleState, touched: Touched, x: np.ndarray | None = None,
                        shared: bool = True) -> np.ndarray:
        """A volume fraction of each (particle, cell) pair that varies smoothly with the particle's
        position: a linear ramp of the cell centre's distance to the sphere surface over the cell's
        extent along the normal (h Σ|n_i|, exact for a plane cutting a cube), shared like α.
        ``x``: the particles' centres, if not where ``state`` has them now."""
        r = self.mesh.cell_center[touched.cell] - (state.x if x is None else x)[touched.particle]
        distance = np.maximum(np.linalg.norm(r, axis=1), 1e-300)
        extent = np.sqrt(self.h2[touched.cell]) * np.abs(r).sum(axis=1) / distance
        fraction = np.clip(0.5 - (distance - state.radius[touched.particle]) / extent, 0.0, 1.0)
        if not shared:
            return fraction
        total = np.bincount(touched.cell, fraction, minlength=self.mesh.n_owned_cells)
        return fraction / np.maximum(total[touched.cell], 1.0)

    def fluid_under(self, state, touched, u, mass, x=None, extra=None):
        """Collective. (n, 6): the momentum of the fluid under each particle, Σ m u over its pairs,
        ``mass`` m = ρ f V with f the smooth fraction (``under_mass`` for this step's pairs), and its
        moment r × about the centre, scaled to the sphere's own volume (``under_scale``: Σ f V
        wobbles by ~1e-3 as the sphere moves, which in a uniform stream gave a particle an impulse
        out of nothing). ``x``: the centres, if not where ``state`` has them. ``extra``: a per-pair
        momentum (m, 3) summed in the same reduction, returned second."""
        p, c = touched.particle, touched.cell
        x = state.x if x is None else x
        covered, _, sums = self.particle_sums(len(state), p, self.mesh.cell_center[c] - x[p], mass,
                                              mass[:, None] * u[c], *(() if extra is None else (extra,)))
        self.under_scale = self.rho * state.volume / np.maximum(covered, np.finfo(float).tiny)
        under = self.under_scale[:, None] * sums[0]
        return under if extra is None else (under, sums[1])

    def penalty_exchange(self, state, touched, u, dt, external_force, external_torque, last, step, time):
        """Collective. The particles' share of a penalized step.

        The hydrodynamic impulse on a particle is what the penalty took from the fluid, J = Σ ρ V κ dt
        (u − U), plus the change ΔP of the momentum of the fluid under the particle (``begin_step``;
        the force on that fluid's surface is the force on the particle's; without ΔP the fluid inside
        would add ρ_f V to the particle's inertia). Each pass before the projection makes a new guess,

            (m + M_c) V_next = m Vⁿ + dt F_ext + J + ΔP + M_c V_guess,   M_c = Σ ρ V κ dt / (1 + κ dt),

        (ω likewise with the moment of M_c): particle and fluid solved together, damped by the cells'
        own response to the particle's speed, an upper bound of the true one, so that the passes
        converge without overshoot; at convergence it is m ΔV = dt F_ext + J + ΔP. After the
        projection (``last``) ΔP includes its pressure, and J is taken at the projected u (the
        projection's correction is damped by the implicit penalty, ``FlowSolver.step``, so that is
        what the fluid gave up); particles with m ≥ M_c then take exactly
        J + ΔP (momentum conserved), lighter ones keep the damped update (``update = "explicit"``:
        always exactly, and every pass penalizes the step's first motion, as the paper's single
        patch does).
        """
        n = len(state)
        p, c = touched.particle, touched.cell
        r = self.mesh.cell_center[c] - state.x[p]
        m, inertia, free = state.mass, state.inertia, state.movable
        if not last:
            kappa = self.kappa
            rigid = self.patched_v[p] + np.cross(self.patched_omega[p], r)
            volume = self.rho * self.mesh.cell_volume[c]
            # two-way: u holds the penalty already (implicit); one-way: the fluid is not forced, and
            # the particle takes what a local implicit penalty would exchange
            kappa_cell = np.bincount(c, kappa, minlength=self.mesh.n_owned_cells)[c]
            rate = kappa * dt if self.two_way else kappa * dt / (1.0 + kappa_cell * dt)
            # how much J falls when the particle speeds up, from each cell's own response: an upper
            # bound (diffusion to the neighbours, and ΔP, lower it), so the passes converge monotonically
            response = volume * kappa * dt / (1.0 + kappa_cell * dt)
            self.exchange_weight = volume * rate
            self.response, self.response_spin, (exchanged, internal) = self.particle_sums(
                n, p, r, response, self.exchange_weight[:, None] * (u[c] - rigid), self.under_mass[:, None] * u[c])
            self.exchanged = exchanged                         # J of this pass's solve
            self.pending[:] = exchanged + self.under_scale[:, None] * internal - self.internal_start   # J + ΔP
            self.solved_v, self.solved_omega = self.patched_v, self.patched_omega
            if self.explicit:
                return None
            impulse, damping, damping_spin = self.pending, self.response, self.response_spin
            v = (m[:, None] * state.v + dt * external_force + impulse[:, :3]
                 + damping[:, None] * self.solved_v) / (m + damping)[:, None]
            omega = (inertia[:, None] * state.omega + dt * external_torque + impulse[:, 3:]
                     + damping_spin[:, None] * self.solved_omega) / (inertia + damping_spin)[:, None]
            self.patched_v = np.where(free[:, None], v, state.v)
            self.patched_omega = np.where(free[:, None], omega, state.omega)
            return None
        # after the projection: ΔP with the projected velocities, and (two-way) J too: the projection's
        # correction is damped by the implicit penalty like the predictor (FlowSolver.step), so the
        # fluid gave up Σ ρ V κ dt (u − U) at the projected u
        if self.two_way:
            rigid = self.solved_v[p] + np.cross(self.solved_omega[p], r)
            internal_end, self.exchanged = self.fluid_under(state, touched, u, self.under_mass,
                                                            extra=self.exchange_weight[:, None] * (u[c] - rigid))
        else:
            internal_end = self.fluid_under(state, touched, u, self.under_mass)
        order = np.argsort(state.id)
        self.internal_end = (state.id[order], internal_end[order], state.x[order].copy())
        impulse = self.exchanged + internal_end - self.internal_start
        momentum, angular = impulse[:, :3], impulse[:, 3:]
        # exact when the particle outweighs the cells' response (on coarse meshes several times
        # ρf V: at 2 cells per diameter a ρp/ρf = 1.2 sphere blew up when ρf V decided)
        exact = np.full(n, self.explicit) | (m >= self.response)
        exact_spin = np.full(n, self.explicit) | (inertia >= self.response_spin)
        damping = np.where(exact, 0.0, self.response)
        damping_spin = np.where(exact_spin, 0.0, self.response_spin)
        dv = (dt * external_force + momentum + damping[:, None] * (self.solved_v - state.v)) / (m + damping)[:, None]
        dw = (dt * external_torque + angular + damping_spin[:, None] * (self.solved_omega - state.omega)
              ) / (inertia + damping_spin)[:, None]
        return self.finish_step(state, dv, dw, momentum, angular, dt, external_force, external_torque, step, time)

    def finish_step(self, state, dv, dw, momentum, angular, dt, external_force, external_torque, step, time):
        """The step's hydrodynamic force and torque on each particle from its velocity changes (free
        particles) or the impulse exchanged (fixed and prescribed ones); ends the step's passes."""
        free = state.movable
        self.pending = None
        force = np.where(free[:, None], state.mass[:, None] * dv / dt - external_force, momentum / dt)
        torque = np.where(free[:, None], state.inertia[:, None] * dw / dt - external_torque, angular / dt)
        if self.explicit:
            self.watch_ringing(state, np.where(free[:, None], dv, 0.0), step, time)
        return force, torque

    def particle_sums(self, n, p, r, mass, *momenta):
        """Collective. Per particle, summed over all ranks in one Allreduce: the ``mass`` of its pairs,
        that mass's moment of inertia about the centre (isotropic share, 2/3 |r|²), and for each
        per-pair momentum vector its sum and its moment r × it (n, 6)."""
        sums = np.zeros((n, 2 + 6 * len(momenta)))
        sums[:, 0] = np.bincount(p, mass, minlength=n)
        sums[:, 1] = np.bincount(p, mass * (2.0 / 3.0) * np.einsum("ij,ij->i", r, r), minlength=n)
        for i, momentum in enumerate(momenta):
            spin = np.cross(r, momentum)
            for d in range(3):
                sums[:, 2 + 6 * i + d] = np.bincount(p, momentum[:, d], minlength=n)
                sums[:, 5 + 6 * i + d] = np.bincount(p, spin[:, d], minlength=n)
        if self.comm.size > 1:
            self.comm.Allreduce(MPI.IN_PLACE, sums, op=MPI.SUM)
        return sums[:, 0], sums[:, 1], [sums[:, 2 + 6 * i: 8 + 6 * i] for i in range(len(momenta))]

    # -- 2b. exchange: drag, torque, the particle update and the patch ---------------------------
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
        if self.penalty:
            return self.penalty_exchange(state, touched, u, dt, external_force, external_torque, last, step, time)
        n = len(state)
        mesh = self.mesh
        p, c = touched.particle, touched.cell
        alpha = self.shared_alpha(touched)
        r = mesh.cell_center[c] - state.x[p]
        mass = self.rho * alpha * mesh.cell_volume[c]
        # the velocities patched by the last pass (this step's start for the first): the deviation
        # from them is the momentum this pass exchanges
        self.start_passes(state)
        rigid = self.patched_v[p] + np.cross(self.patched_omega[p], r)
        covered, moment, (deviation,) = self.particle_sums(n, p, r, mass, mass[:, None] * (u[c] - rigid))
        self.pending += deviation
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
        return self.finish_step(state, dv, dw, momentum, angular, dt, external_force, external_torque, step, time)

    def carry_fluid(self, state: ParticleState, touched: Touched, u: np.ndarray, fresh: np.ndarray) -> None:
        """Local (owned rows of ``u``). Particles new to the flow (present at the start, or just
        injected): the fluid they cover is the solver's, not the user's, so it starts moving with
        them. Otherwise a particle released at speed into still fluid would spend its first step
        accelerating its own volume of fluid (a ρp/ρf = 2 sphere lost half its momentum so).
        The penalty forcing needs none of this: its impulse leaves out the fluid under the particle
        (ΔP in ``penalty_exchange``), so that fluid's start from rest costs the particle nothing."""
        if not self.two_way or self.penalty:
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


PENALTY_CAP = 1e3   # κ h²/ν of a cell wholly inside a particle: rigid to ~1e-3 of its neighbours' pull;
                    # larger caps inflate ‖b‖ of the momentum solves, whose rtol is relative to it


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
