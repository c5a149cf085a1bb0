"""The paper's patch forcing (``[coupling] forcing = "patch"``, eq. 1–2).

After each momentum solve, u ← (1 − α) u + α U in the touched cells, U = V + ω × r the particle's
rigid motion, and once more after the projection; the momentum the patches add to the fluid is
taken from the particles (drag and torque), with the update of ``update.blended_change``

    (m + (1 − θ) M) (Vⁿ⁺¹ − Vⁿ) = dt F_ext + M (ū* − Vⁿ),     θ = min(1, m/M),

M the covered fluid mass and ū* the predicted fluid velocity under the particle (θ = 1 is the
paper's explicit update, which rings for light particles). Each pass patches the updated motion,
so particle and fluid converge together; the patch's momentum becomes a source of the next solve
(multi-direct forcing). Re-blending the cut cells every step makes its forces depend on ν dt/h².
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..fluid import FluidState
from ..particles import ParticleState
from .holders import Holders
from .locate import CellLocator, Touched, shared_alpha
from .memory import CouplingMemory
from .sums import fluid_sums
from .update import Exchange, External, blended_change, hydrodynamic_force, watch_ringing


@dataclass(frozen=True)
class PatchPasses:
    """One step of the patch forcing, handed from pass to pass: the pairs' shared α (m,), arm r
    from the centre (m, 3) and covered fluid mass (m,); the motion the last pass patched (n, 3);
    the momentum all passes so far took from the fluid, with its moment (n, 6); where the
    per-particle sums meet (``holders.Holders``)."""

    touched: Touched
    alpha: np.ndarray
    r: np.ndarray
    mass: np.ndarray
    guess_v: np.ndarray
    guess_omega: np.ndarray
    pending: np.ndarray
    holders: Holders


class PatchForcing:
    """The paper's patch on one mesh (see the module docstring). Holds its settings only.

    Parameters
    ----------
    mesh : pmpm.mesh.Mesh
    section : the case's [coupling] section
    fluid_density : ρ_f (kg/m³)
    """

    def __init__(self, mesh, section, fluid_density: float):
        self.mesh, self.comm = mesh, mesh.comm
        self.locator = CellLocator(mesh, section.volume_fraction, int(section.subcell_points), smooth_reach=False)
        self.rho = float(fluid_density)
        self.two_way = section.mode == "two-way"
        self.explicit = section.update == "explicit"

    def locate(self, state: ParticleState) -> Touched:
        """Local. This rank's touched cells and volume fractions."""
        return self.locator.locate(state)

    def begin(self, state: ParticleState, touched: Touched, fluid: FluidState, memory: CouplingMemory,
              dt: float, holders: Holders | None = None) -> tuple[PatchPasses, FluidState]:
        """Collective. The step's pairs; particles new to the flow (present at the start, or just
        injected; ids above ``memory.known_id``) first bring the fluid they cover up to their motion:
        it is the solver's fluid, not the user's, and a particle released at speed into still fluid
        would otherwise spend its first step accelerating it. ``holders``: where the per-particle
        sums meet (default: every rank holds every particle)."""
        n_owned = self.mesh.n_owned_cells
        holders = holders if holders is not None else Holders.everywhere(self.comm, len(state))
        p, c = touched.particle, touched.cell
        alpha = shared_alpha(touched, n_owned)
        r = self.mesh.cell_center[c] - state.x[p]
        fresh = state.id > memory.known_id
        if self.two_way and holders.largest(int(fresh.any())):   # (a collective: every rank, or none)
            pick = fresh[p]
            u = patched(fluid.u, c[pick], alpha[pick],
                        state.v[p[pick]] + np.cross(state.omega[p[pick]], r[pick]), n_owned)
            fluid = replace(fluid, u=self.mesh.update_ghosts(u))
        passes = PatchPasses(touched, alpha, r, self.rho * alpha * self.mesh.cell_volume[c], state.v, state.omega,
                             np.zeros((len(state), 6)), holders)
        return passes, fluid

    def implicit_terms(self, state: ParticleState, passes: PatchPasses):
        """The patch adds nothing to the momentum matrices."""
        return None, None

    def exchange(self, state: ParticleState, passes: PatchPasses, u: np.ndarray, external: External, dt: float,
                 last: bool):
        """Collective. One patch: the momentum of u's deviation from the last patched motion joins
        the step's; the particle update from all of it; in two-way mode u patched with the updated
        motion (a new array). Returns (u, passes, dv, dw)."""
        p, c = passes.touched.particle, passes.touched.cell
        covered, moment, _, deviation = fluid_sums(passes.holders, len(state), p, c, passes.r, u, passes.mass,
                                                    passes.mass, passes.guess_v, passes.guess_omega)
        pending = passes.pending + deviation
        dv, dw = blended_change(state, external, pending, dt, covered, moment, self.explicit)
        free = state.movable
        new_v = np.where(free[:, None], state.v + dv, state.v)
        new_omega = np.where(free[:, None], state.omega + dw, state.omega)
        if self.explicit and not last:   # the paper's update: every pass patches the step's first motion
            new_v, new_omega = passes.guess_v, passes.guess_omega
        if self.two_way:
            u = patched(u, c, passes.alpha, new_v[p] + np.cross(new_omega[p], passes.r), self.mesh.n_owned_cells)
        return u, replace(passes, guess_v=new_v, guess_omega=new_omega, pending=pending), dv, dw

    def after_solve(self, state: ParticleState, passes: PatchPasses, u_star: np.ndarray, external: External,
                    dt: float) -> tuple[np.ndarray, np.ndarray | None, PatchPasses]:
        """Collective. The patch after a momentum solve: the patched u* (its owned rows change), and
        the momentum the patch added, V (u*_patched − u*)/dt (n_owned, 3), a source for a next solve
        (multi-direct forcing: the rigid motion then holds after that solve too); None in one-way mode."""
        patched_u, passes, _, _ = self.exchange(state, passes, u_star, external, dt, last=False)
        if not self.two_way:
            return u_star, None, passes
        n_owned = self.mesh.n_owned_cells
        source = self.mesh.cell_volume[:n_owned, None] * (patched_u[:n_owned] - u_star[:n_owned]) / dt
        return patched_u, source, passes

    def after_projection(self, state: ParticleState, passes: PatchPasses, fluid: FluidState, external: External,
                         dt: float, memory: CouplingMemory, step: int, time: float) -> Exchange:
        """Collective. The patch after the projection, which let fluid into the particles; the
        step's drag and torque from all the momentum the patches took."""
        u, passes, dv, dw = self.exchange(state, passes, fluid.u, external, dt, last=True)
        if self.two_way:
            fluid = replace(fluid, u=self.mesh.update_ghosts(u))
        force, torque = hydrodynamic_force(state, external, dv, dw, passes.pending, dt)
        known = passes.holders.largest(int(state.id.max(initial=-1)))   # (the same on every rank)
        memory = replace(memory, known_id=max(memory.known_id, known))
        if self.explicit:
            memory = watch_ringing(state, np.where(state.movable[:, None], dv, 0.0), memory, self.rho, step, time,
                                   passes.holders)
        return Exchange(fluid, force, torque, memory)


def patched(u: np.ndarray, cell: np.ndarray, alpha: np.ndarray, target: np.ndarray, n_owned: int) -> np.ndarray:
    """A copy of u with u ← (1 − α) u + α target in the touched owned cells (eq. 1's velocity patch)."""
    u = u.copy()
    change = alpha[:, None] * (target - u[cell])
    for d in range(3):
        u[:n_owned, d] += np.bincount(cell, change[:, d], minlength=n_owned)
    return u
