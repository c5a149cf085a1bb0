"""The penalty forcing (``[coupling] forcing = "penalty"``, the default).

A penalty κ (U − u) drives the fluid in a touched cell towards the particle's rigid motion
U = V + ω × r, solved implicitly with the diffusion of the momentum predictor (V κ on the
diagonal, V κ U on the right-hand side: ``implicit_terms``; the flow solver damps its pressure
terms in those cells by 1/(1 + κ dt) as well). Its rate has two parts (``penalty_rates``): the
solid's friction s α/(1 − α) ν/h² (``penalty_strength`` s, α the cell's volume fraction), which in
a cut cell balances the fluid's own viscous exchange, a balance without dt in it, so the forces
hardly depend on the time step; and a blockage rate (1000/6) α⁸ U_rel/h that stops, in the cells
a particle fills, the flow the pressure drives through it, whatever the cell Reynolds number.

The impulse on a particle is what the penalty took from the fluid, J = Σ ρ V κ dt (u − U) at the
projected u, plus the change ΔP of the momentum of the fluid under it, over a control volume that moves with the particle
(``begin``: from where the last step left it). Each pass before the projection updates the guess of
the particle's new motion, damped by the cells' own response so that light particles converge
(``after_solve``); after the projection the step's impulse gives its velocities, drag and torque
(``after_projection``). With ``drag_correction`` (``correction.py``) an extra rate κ_x acts on
the fluid share of each particle's cells, or a relief force pushes particles whose resolved drag is
too high against their slip and the fluid around them along it (``relief``); ``corrected_rates``
sets the next step's from the drag the particles felt. docs/coupling.md has the method's measurements.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from ..arrays import cross, sum_rows, summed
from ..fluid import FluidState
from ..particles import ParticleState
from .holders import Holders
from .locate import CellLocator, Touched, alpha_per_cell, shared_smooth
from .memory import CouplingMemory, by_id
from .sums import cell_targets, fluid_sums, largest_slip
from .update import Exchange, External, damped_change, damped_guess, hydrodynamic_force, watch_ringing

PENALTY_CAP = 1e3   # κ h²/ν of a cell wholly inside a particle: rigid to ~1e-3 of its neighbours' pull;
                    # larger caps inflate ‖b‖ of the momentum solves, whose rtol is relative to it


def cell_rate(covered: np.ndarray, speed: np.ndarray, nu: float, h2: np.ndarray, strength: float) -> np.ndarray:
    """κ (1/s) of cells a solid covers by the fractions ``covered`` (≤ 1), met by the flow at
    ``speed`` (m/s), of squared size ``h2`` (m²): friction min(s α/(1 − α), 1000) ν/h² plus blockage
    (1000/6) α⁸ speed/h (``PenaltyForcing.penalty_rates``)."""
    friction = np.minimum(strength * covered / np.maximum(1.0 - covered, 1e-300), PENALTY_CAP)
    blockage = PENALTY_CAP / 6.0 * covered ** 8 * speed / np.sqrt(h2)
    return friction * nu / h2 + blockage


@dataclass(frozen=True)
class PenaltyPasses:
    """One step of the penalty forcing, handed from pass to pass.

    touched : the step's (particle, cell, α) pairs on this rank
    offset : (m, 3) r from the particle's centre to the cell centre; the particles stay put during
        the flow step
    kappa : (m,) κ of each pair (1/s)
    under_mass : (m,) ρ f V, the fluid mass under the particle in each pair (f the smooth fraction)
    under_scale : (n,) ρ V_sphere / Σ under_mass: "under" scaled to the sphere's own volume
    internal_start : (n, 6) the fluid momentum under each particle at the step's start, with its moment
    exchange_weight : (m,) ρ V × the rate of the exchange per pair (J = Σ weight (u − U))
    response, response_spin : (n,) the cells' response M_c to the particle's speed and spin
    guess_v, guess_omega : (n, 3) the motion the next solve drives the fluid towards
    solved_v, solved_omega : (n, 3) the motion the last solve drove it towards
    exchanged : (n, 6) J of the last solve
    relief : (n, 3) the drag correction's relief force on each particle (N), or None
    relief_source : (n_owned, 3) the same force put into the fluid around the particles (N/ρ per cell),
        or None
    holders : where the per-particle sums meet (``holders.Holders``)
    """

    touched: Touched
    offset: np.ndarray
    kappa: np.ndarray
    under_mass: np.ndarray
    under_scale: np.ndarray
    internal_start: np.ndarray
    exchange_weight: np.ndarray
    response: np.ndarray
    response_spin: np.ndarray
    guess_v: np.ndarray
    guess_omega: np.ndarray
    solved_v: np.ndarray | None = None
    solved_omega: np.ndarray | None = None
    exchanged: np.ndarray | None = None
    relief: np.ndarray | None = None
    relief_source: np.ndarray | None = None
    holders: Holders | None = None


class PenaltyForcing:
    """The penalty forcing on one mesh (see the module docstring). Holds its settings only.

    Parameters
    ----------
    mesh : pmpm.mesh.Mesh
    section : the case's [coupling] section
    fluid_density : ρ_f (kg/m³)
    viscosity : μ (Pa s)
    correction : the drag correction for under-resolved particles (``correction.DragCorrection``), or None
    """

    def __init__(self, mesh, section, fluid_density: float, viscosity: float, correction=None):
        self.mesh, self.comm = mesh, mesh.comm
        self.locator = CellLocator(mesh, section.volume_fraction, int(section.subcell_points), smooth_reach=True)
        self.rho = float(fluid_density)
        self.nu = float(viscosity) / self.rho
        self.two_way = section.mode == "two-way"
        self.explicit = section.update == "explicit"
        self.strength = float(section.penalty_strength)
        self.correction = correction

    def locate(self, state: ParticleState) -> Touched:
        """Local. This rank's touched cells and volume fractions."""
        return self.locator.locate(state)

    def begin(self, state: ParticleState, touched: Touched, fluid: FluidState, memory: CouplingMemory,
              dt: float, holders: Holders | None = None) -> tuple[PenaltyPasses, FluidState]:
        """Collective. The step's rates and the fluid momentum under each particle at its start.
        ``holders``: where the per-particle sums meet (default: every rank holds every particle).

        The fluid inside a moving particle is a control volume that moves with it, so its momentum
        change includes what the particle's advance covered and uncovered (Reynolds transport): the
        start is the fluid under the particle *as the last step left it* (``memory``). Over a fixed
        set of cells instead, the fluid a moving sphere sweeps up ahead and leaves behind gave it a
        thrust. "Under" weighs each cell by a smooth fraction, not α, whose jumps as sample points
        cross the surface made light particles ring. The flow is returned as it came.

        The exchange's weights and the cells' response M_c = Σ ρ V K (1 + K_o)/(1 + K + K_o), K = κ dt
        the particle's and K_o the other particles' in the cell (how much J falls when the particle
        speeds up: an upper bound, since diffusion to the neighbours and ΔP lower it, so that the
        passes converge monotonically) hold for the whole step."""
        n_owned = self.mesh.n_owned_cells
        holders = holders if holders is not None else Holders.everywhere(self.comm, len(state))
        p, c = touched.particle, touched.cell
        offset = self.mesh.cell_center[c] - state.x[p]
        speed = largest_slip(holders, len(state), p, c, offset, fluid.u, state.v, state.omega)
        kappa = self.penalty_rates(touched, speed)
        if self.correction is not None:   # the extra rate acts on the fluid share of the particle's cells
            total = alpha_per_cell(touched, n_owned)[c]
            kappa = kappa + self.correction.rates(state, memory)[p] * (1.0 - np.minimum(total, 1.0))
        under_mass = self.rho * shared_smooth(touched, n_owned) * self.mesh.cell_volume[c]
        internal_start, under_scale = self.fluid_under(state, touched, offset, fluid.u, under_mass, holders)[:2]
        volume = self.rho * self.mesh.cell_volume[c]
        kappa_cell = np.bincount(c, kappa, minlength=n_owned)[c]
        # one-way: the particle takes what a local implicit penalty would exchange
        rate = kappa * dt if self.two_way else kappa * dt / (1.0 + kappa_cell * dt)
        # two-way: a cell the particle shares is held by the others' penalties too, K_o = (κ_cell − κ) dt,
        # which resist its own motion there: ∂J/∂U = ρ V K (1 + K_o)/(1 + K + K_o). Without K_o, two
        # beads touching across cells they both fill had passes that overshot their relative motion
        # and rang, growing ×3 a step, once the blockage rate made K and K_o tens (a settling bed at
        # dt = 1 ms; docs/coupling.md, "Dense suspensions")
        others = (kappa_cell - kappa) * dt if self.two_way else 0.0
        response, response_spin = fluid_sums(holders, len(state), p, c, offset, fluid.u,
                                             volume * kappa * dt * (1.0 + others) / (1.0 + kappa_cell * dt))[:2]
        if memory.under_id is not None:   # particles new to the flow keep the fluid under them now
            position, same = by_id(memory.under_id, state.id)
            start = memory.under_momentum[position[same]].copy()
            # its moment about where the centre is now: L' = L − (x' − x) × P
            start[:, 3:] -= np.cross(state.x[same] - memory.under_centre[position[same]], start[:, :3])
            internal_start[same] = start
            holders.from_owners(internal_start)   # (a new ghost here remembers nothing; its owner does)
        relief = relief_source = None
        if self.correction is not None:
            relief, relief_source = self.relief(state, touched, memory, holders)
        return PenaltyPasses(touched, offset, kappa, under_mass, under_scale, internal_start, volume * rate, response,
                             response_spin, state.v, state.omega, relief=relief, relief_source=relief_source,
                             holders=holders), fluid

    def relief(self, state: ParticleState, touched: Touched, memory: CouplingMemory, holders: Holders):
        """Collective. The drag correction's relief (``correction.py``): the force on each particle
        (n, 3) N, and the opposite force on the fluid around it, (n_owned, 3) per cell (divided by ρ,
        as the momentum equations' right-hand sides), shared among the particle's cells by their
        volume outside every particle's control volume, so that the fluid under a particle, whose
        change the particle takes, does not hand it back. A particle with no such cell takes none.
        (None, None) where no pool relieves."""
        relief = self.correction.relief(state, memory)
        if relief is None:
            return None, None
        holders.from_owners(relief)
        n_owned = self.mesh.n_owned_cells
        p, c = touched.particle, touched.cell
        under = np.bincount(c, touched.smooth, minlength=n_owned)[c]
        outside = self.mesh.cell_volume[c] * np.maximum(1.0 - under, 0.0)
        total = holders.sum(summed(p, outside, len(state)))
        relief = np.where((total > 0.0)[:, None], relief, 0.0)
        share = outside / np.where(total > 0.0, total, 1.0)[p]
        return relief, sum_rows(c, -share[:, None] * relief[p] / self.rho, n_owned)

    def penalty_rates(self, touched: Touched, speed: np.ndarray) -> np.ndarray:
        """κ (1/s) of each (particle, cell) pair, from the cell's total volume fraction α, shared among
        the particles in it by their α:

            κ = min(s α/(1 − α), 1000) ν/h²  +  (1000/6) α⁸ |u − U|_max / h.

        The first term is the solid's viscous friction on the fluid in the cell (s =
        ``penalty_strength``, fitted on the Stokes drag): it sets where the particle's surface lies,
        without dt. The second is the blockage: a cell the particle fills must stop the flow that the
        pressure drives through it, ∇p/ρ ~ |u − U|²/d, faster than convection brings it; ``speed``
        (n,) |u − U|_max is each particle's over its cells at the step's start. A cell wholly inside gets 167 times
        either exchange rate with its neighbours (6 ν/h² by diffusion, |u − U|/h by convection); α⁸
        leaves the friction of the cut cells viscous, so the surface stays where the Stokes fit put it."""
        total = alpha_per_cell(touched, self.mesh.n_owned_cells)[touched.cell]
        rate = cell_rate(np.minimum(total, 1.0), speed[touched.particle], self.nu, self.locator.h2[touched.cell],
                         self.strength)
        return rate * touched.alpha / np.maximum(total, 1e-300)

    def implicit_terms(self, state: ParticleState, passes: PenaltyPasses):
        """Local. (V κ (n_owned,), V κ U (n_owned, 3)) per owned cell for the next momentum solve, U
        the rigid motion of the current guess; (None, None) in one-way mode: the fluid is not forced."""
        if not self.two_way:
            return None, None
        touched = passes.touched
        diagonal, target = cell_targets(self.mesh.n_owned_cells, touched.particle, touched.cell, passes.offset,
                                        self.mesh.cell_volume[touched.cell] * passes.kappa, passes.guess_v,
                                        passes.guess_omega)
        return diagonal, target if passes.relief_source is None else target + passes.relief_source

    def after_solve(self, state: ParticleState, passes: PenaltyPasses, u_star: np.ndarray, external: External,
                    dt: float) -> tuple[np.ndarray, None, PenaltyPasses]:
        """Collective. After a momentum solve: J of this solve and the next guess,

            (m + M_c) V_next = m Vⁿ + dt F_ext + J + ΔP + M_c V_guess,   M_c the cells' response (``begin``),

        damped by the cells' own response to the particle's speed, an upper bound of the true one,
        so that the passes converge without overshoot; at convergence m ΔV = dt F_ext + J + ΔP.
        (``update = "explicit"``: no new guess; every pass drives the fluid towards the step's first
        motion, as the paper's single patch does.) ``u_star`` is returned unchanged, with no source
        for the next solve: the penalty is already in it (two-way) or the fluid is not forced (one-way)."""
        internal, _, exchanged = self.fluid_under(state, passes.touched, passes.offset, u_star, passes.under_mass,
                                                  passes.holders, passes.exchange_weight, passes.guess_v,
                                                  passes.guess_omega)
        passes = replace(passes, solved_v=passes.guess_v, solved_omega=passes.guess_omega, exchanged=exchanged)
        if self.explicit:
            return u_star, None, passes
        impulse = with_relief(exchanged + internal - passes.internal_start, passes.relief, dt)   # J + ΔP
        v, omega = damped_guess(state, external, impulse, dt, passes.response, passes.response_spin,
                                passes.solved_v, passes.solved_omega)
        return u_star, None, replace(passes, guess_v=v, guess_omega=omega)

    def after_projection(self, state: ParticleState, passes: PenaltyPasses, fluid: FluidState, external: External,
                         dt: float, memory: CouplingMemory, step: int, time: float) -> Exchange:
        """Collective. The step's impulse J + ΔP, ΔP now with the projected velocities, and (two-way)
        J too: the projection's correction is damped by the implicit penalty like the predictor
        (``FlowSolver.correct``), so the fluid gave up Σ ρ V κ dt (u − U) at the projected u.
        Particles with m ≥ M_c take it exactly (momentum conserved; M_c, not ρf V, decides: on coarse
        meshes it is several times ρf V), lighter ones keep the damped update of the last pass
        (``update = "explicit"``: always exactly)."""
        n = len(state)
        exchanged = passes.exchanged
        if self.two_way:
            internal_end, _, exchanged = self.fluid_under(state, passes.touched, passes.offset, fluid.u,
                                                          passes.under_mass, passes.holders, passes.exchange_weight,
                                                          passes.solved_v, passes.solved_omega)
        else:
            internal_end = self.fluid_under(state, passes.touched, passes.offset, fluid.u, passes.under_mass,
                                            passes.holders)[0]
        order = np.argsort(state.id)
        impulse = with_relief(exchanged + internal_end - passes.internal_start, passes.relief, dt)
        m, inertia = state.mass, state.inertia
        exact = np.full(n, self.explicit) | (m >= passes.response)
        exact_spin = np.full(n, self.explicit) | (inertia >= passes.response_spin)
        damping = np.where(exact, 0.0, passes.response)
        damping_spin = np.where(exact_spin, 0.0, passes.response_spin)
        dv, dw = damped_change(state, external, impulse, dt, damping, damping_spin, passes.solved_v,
                               passes.solved_omega)
        force, torque = hydrodynamic_force(state, external, dv, dw, impulse, dt)
        memory = replace(memory, under_id=state.id[order], under_momentum=internal_end[order],
                         under_centre=state.x[order])
        if self.correction is not None:
            v = np.where(state.movable[:, None], state.v + dv, state.v)
            rate, relief, target = self.corrected_rates(state, passes, fluid.u, v, force, dt, memory)
            memory = replace(memory, correction_rate=rate, correction_relief=relief, under_target=target[order])
        if self.explicit:
            memory = watch_ringing(state, np.where(state.movable[:, None], dv, 0.0), memory, self.rho, step, time,
                                   passes.holders)
        return Exchange(fluid, force, torque, memory)

    def corrected_rates(self, state: ParticleState, passes: PenaltyPasses, u: np.ndarray, v: np.ndarray,
                        force: np.ndarray, dt: float, memory: CouplingMemory):
        """Collective. The drag correction's κ_x and relief β per pool of particles (n_pools,) for the
        next step, and the correlation's force on each particle (n, 3) N, from the correlation at the
        local voidage and slip (particle velocities ``v`` (n, 3) at the step's end, flow ``u``), the
        drag ``force`` (n, 3) felt this step, and the force per unit κ_x in the particle's cells: the
        fluid share (1 − α) of each, its velocity relative to the particle, damped by the cell's own
        implicit response 1/(1 + κ dt)."""
        touched, n_owned = passes.touched, self.mesh.n_owned_cells
        p, c = touched.particle, touched.cell
        alpha = alpha_per_cell(touched, n_owned)
        rigid = passes.solved_v[p] + cross(passes.solved_omega[p], passes.offset)
        solid = sum_rows(c, touched.alpha[:, None] * rigid, n_owned)
        eps, superficial = self.correction.slip(state, u, alpha, solid, v)
        kappa_cell = np.bincount(c, passes.kappa, minlength=n_owned)[c]
        along = np.einsum("ij,ij->i", u[c] - rigid, superficial[p])
        share = self.rho * self.mesh.cell_volume[c] * (1.0 - np.minimum(alpha[c], 1.0)) * along / (1 + kappa_cell * dt)
        n = len(state)   # the sensitivity along U_s, and the particle's cell size (α-weighted)
        sums = passes.holders.sum(np.stack([summed(p, share, n), summed(p, touched.alpha * self.locator.h[c], n),
                                            summed(p, touched.alpha, n)], axis=1))
        sums = sums.T
        h = sums[1] / np.maximum(sums[2], np.finfo(float).tiny)
        target, direction, relievable = self.correction.target(state, eps, superficial, h)
        target *= np.minimum(1.0, 1.0 / passes.under_scale)    # the share of a sphere cut by a symmetry plane
        sensitivity = sums[0] / np.maximum(np.linalg.norm(superficial, axis=1), np.finfo(float).tiny)
        n_pools = self.correction.bins.n_pools
        rate = np.zeros(n_pools) if memory.correction_rate is None else memory.correction_rate
        relief = np.zeros(n_pools) if memory.correction_relief is None else memory.correction_relief
        rate, relief = self.correction.update(state, rate, relief, eps, target, direction, relievable, force,
                                              sensitivity, dt, passes.holders)
        return rate, relief, (relievable * target)[:, None] * direction

    def fluid_under(self, state: ParticleState, touched: Touched, offset: np.ndarray, u: np.ndarray,
                    mass: np.ndarray, holders: Holders, weight: np.ndarray | None = None, v: np.ndarray | None = None,
                    omega: np.ndarray | None = None):
        """Collective. The momentum of the fluid under each particle, (n, 6): Σ m u over its pairs
        (``mass`` m = ρ f V, f the smooth fraction) and its moment about the centre, scaled to the
        sphere's own volume (Σ f V wobbles by ~1e-3 as the sphere moves, which in a uniform stream
        gave a particle an impulse out of nothing); that scale (n,); and, with a ``weight`` per pair
        and the particles' motion ``v``, ``omega``, the exchange Σ weight (u − U) with its moment
        (n, 6) (else None). ``offset`` (m, 3): from the particle's centre to each pair's cell centre;
        ``holders``: where the sums meet."""
        covered, _, carried, exchanged = fluid_sums(holders, len(state), touched.particle, touched.cell, offset, u,
                                                    mass, weight, v, omega)
        scale = self.rho * state.volume / np.maximum(covered, np.finfo(float).tiny)
        return scale[:, None] * carried, scale, exchanged


def with_relief(impulse: np.ndarray, relief: np.ndarray | None, dt: float) -> np.ndarray:
    """``impulse`` (n, 6) with the drag correction's relief force (n, 3) over dt added (no torque)."""
    if relief is None:
        return impulse
    out = impulse.copy()
    out[:, :3] += relief * dt
    return out
