"""Incompressible Navier–Stokes on the distributed mesh: an incremental projection method.

Cell-centred finite volumes, collocated u and p. One step of size dt:

1. predictor: (V/dt − ν L) u* = V/dt uⁿ − C(uⁿ) − V ∇pⁿ/ρ + S, with the convection C explicit
   (face flux Fⁿ × upwind, central or linear-upwind face value) and the diffusion ν L implicit
   (one KSP solve per component, matrices assembled once per dt);
2. face flux with a Rhie–Chow-type pressure term, which is what keeps the pressure free of
   checkerboarding: F* = (u* + d ∇pⁿ)‾·S − d̄ (a_f (pⁿ_N − pⁿ_P) + k_f·∇̄pⁿ), d = dt/ρ except in
   cells under a particle's implicit penalty κ, where d = dt/ρ / (1 + κ dt);
3. projection: the pressure correction p' from Σ a_f (p'_P − p'_N) = −ρ/dt Σ F* (PETSc KSP,
   ``pmpm.pressure``), with explicit non-orthogonal correctors k_f·∇̄p' on skewed meshes;
4. correction: F = F* − dt/ρ (a_f Δp' + k_f·∇̄p'), u = u* − d ∇p', p = pⁿ + p'.

Here a_f = |S|²/(d·S) (over-relaxed split, k_f = S − a_f d), bars are face interpolations, and
S is an explicit momentum source (the particles, ``pmpm.coupling``). The face fluxes F are
divergence-free to the KSP tolerance and convect the next step.

Gravity: ``p`` is the pressure less the hydrostatic part ρ g·x, so gravity does not appear in the
fluid equations and still fluid stays still; particles feel buoyancy explicitly (DESIGN.md).

Boundaries (SPEC §3): wall (no-slip, moving surface V + Ω × (x − c)), inlet (velocity),
outlet (fixed pressure, zero-gradient velocity), symmetry (no normal flux, free slip).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
from mpi4py import MPI

from .errors import NumericalError
from .pressure import CellKSP, PressureSolver, assemble_cell_matrix




WALL, INLET, OUTLET, SYMMETRY = 0, 1, 2, 3
BOUNDARY_CODES = {"wall": WALL, "inlet": INLET, "outlet": OUTLET, "symmetry": SYMMETRY}


@dataclass
class FluidState:
    """The flow: cell velocity (n_local, 3), pressure less hydrostatics (n_local,), face flux (n_faces,)."""

    u: np.ndarray
    p: np.ndarray
    flux: np.ndarray


class FlowSolver:
    """Collective. The flow solver of one mesh and case; geometry and matrices are built once.

    Parameters
    ----------
    mesh : pmpm.mesh.Mesh
    fluid : case [fluid] section (density, viscosity, convection, pressure_rtol, nonorthogonal_correctors)
    boundaries : dict name → case [boundary.<name>] section; unlisted boundaries are fixed walls
    """

    def __init__(self, mesh, fluid, boundaries: dict):
        self.mesh = mesh
        self.comm = mesh.comm
        self.rho = float(fluid.density)
        self.nu = float(fluid.viscosity) / self.rho
        self.scheme = fluid.convection
        self.correctors = int(fluid.nonorthogonal_correctors)
        self._geometry()
        self._boundaries(boundaries)
        # pressure: a_f on interior faces, a_b on outlet faces (Dirichlet); assembled once
        coefficient = np.concatenate([self.a, self.a_b])
        dirichlet = np.zeros(len(coefficient), bool)
        dirichlet[self.n_interior:] = self.kind == OUTLET
        self.pressure = PressureSolver(mesh, coefficient, dirichlet, rtol=fluid.pressure_rtol)
        self._momentum_dt = None
        self.momentum = []
        self._penalized = False      # a particle penalty is on the momentum matrices' diagonals
        self.penalty_rate = np.zeros(self.n_local)   # κ (1/s) of the last momentum solve, per cell
        self.last_pressure_iterations = 0

    # -- set-up -------------------------------------------------------------------------------------
    def _geometry(self):
        mesh = self.mesh
        n_int = self.n_interior = mesh.n_interior_faces
        self.n_local, self.n_owned = mesh.n_local_cells, mesh.n_owned_cells
        fc, S, xf, xc = mesh.face_cells, mesh.face_area_vec, mesh.face_center, mesh.cell_center
        self.P, self.N, self.B = fc[:n_int, 0], fc[:n_int, 1], fc[n_int:, 0]
        self.S, self.S_b = S[:n_int], S[n_int:]
        self.xf_b = xf[n_int:]
        self.normal_b = S[n_int:] / mesh.face_area[n_int:, None]
        d = xc[self.N] - xc[self.P]
        d_b = xf[n_int:] - xc[self.B]
        area2 = mesh.face_area ** 2
        self.a = area2[:n_int] / np.einsum("ij,ij->i", d, self.S)
        self.a_b = area2[n_int:] / np.einsum("ij,ij->i", d_b, self.S_b)
        self.k = self.S - self.a[:, None] * d                      # non-orthogonal remainder
        self.k_b = self.S_b - self.a_b[:, None] * d_b
        # weight of the owner cell in face interpolation, from the distances along S
        self.w = np.einsum("ij,ij->i", xc[self.N] - xf[:n_int], self.S) / np.einsum("ij,ij->i", d, self.S)
        self.xf = xf[:n_int]                                       # for linear-upwind reconstruction
        self.volume = mesh.cell_volume
        # signed face → cell sum: (D @ face values)[c] = Σ over c's faces, outward positive
        n_faces = len(fc)
        rows = np.concatenate([self.P, self.N, self.B])
        cols = np.concatenate([np.arange(n_int), np.arange(n_int), np.arange(n_int, n_faces)])
        vals = np.concatenate([np.ones(n_int), -np.ones(n_int), np.ones(n_faces - n_int)])
        self.D = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(self.n_local, n_faces))
        # interior face interpolation as a matrix: one sparse product is 3× faster than two gathers
        faces = np.arange(n_int)
        self.I = scipy.sparse.csr_matrix((np.concatenate([self.w, 1 - self.w]),
                                          (np.concatenate([faces, faces]), np.concatenate([self.P, self.N]))),
                                         shape=(n_int, self.n_local))
        skew = max(np.abs(self.k).max(initial=0.0), np.abs(self.k_b).max(initial=0.0)) / max(mesh.face_area.max(initial=1), 1e-300)
        self.orthogonal = self.comm.allreduce(skew, op=MPI.MAX) < 1e-8
        if self.orthogonal:  # k = 0: no memory for it, and no non-orthogonal terms in the step
            self.k, self.k_b = None, None
        self.h = (mesh.cell_volume ** (1 / 3))

    def _boundaries(self, boundaries):
        """Per boundary face: kind, fixed velocity (walls, inlets) and outlet pressure."""
        names = self.mesh.boundary_names
        index = self.mesh.face_boundary[self.n_interior:]
        self.kind = np.full(len(index), WALL, np.int8)
        self.u_fixed = np.zeros((len(index), 3))
        self.p_out = np.zeros(len(index))
        for i, name in enumerate(names):
            here = index == i
            b = boundaries.get(name)
            if b is None:
                continue
            self.kind[here] = BOUNDARY_CODES[b.type]
            if b.type == "inlet":
                self.u_fixed[here] = b.velocity
            elif b.type == "wall":
                r = self.xf_b[here] - np.asarray(b.center)
                self.u_fixed[here] = np.asarray(b.velocity) + np.cross(np.asarray(b.angular_velocity), r)
            elif b.type == "outlet":
                self.p_out[here] = b.pressure
        # a moving wall's surface slides along itself: only its normal part moves fluid through it
        fixed_flux = np.einsum("ij,ij->i", self.u_fixed, self.S_b)
        self.flux_fixed = np.where((self.kind == WALL) | (self.kind == INLET), fixed_flux, 0.0)
        self.dirichlet_u = (self.kind == WALL) | (self.kind == INLET)

    def initial_state(self) -> FluidState:
        """Fluid at rest, fluxes consistent with the fixed boundary fluxes."""
        flux = np.zeros(len(self.mesh.face_cells))
        flux[self.n_interior:] = self.flux_fixed
        return FluidState(np.zeros((self.n_local, 3)), np.zeros(self.n_local), flux)

    def _momentum_solvers(self, dt: float):
        """The implicit-diffusion matrices (V/dt − ν L) of the three components, for this dt."""
        if self._momentum_dt is not None and abs(self._momentum_dt - dt) <= 1e-12 * dt:
            return self.momentum
        for solver in self.momentum:
            solver.destroy()
        nu = self.nu
        coefficient = np.concatenate([nu * self.a, np.zeros(len(self.a_b))])
        self.momentum = []
        # the three matrices differ only on symmetry faces: without them, one matrix and KSP serve all
        symmetry = self.comm.allreduce(bool((self.kind == SYMMETRY).any()), op=MPI.LOR)
        for component in range(3):
            if component and not symmetry:
                self.momentum.append(self.momentum[0])
                continue
            boundary = nu * self.a_b * np.where(self.dirichlet_u, 1.0, 0.0)
            boundary += nu * self.a_b * np.where(self.kind == SYMMETRY, self.normal_b[:, component] ** 2, 0.0)
            diagonal = self.volume / dt + np.bincount(self.B, boundary, minlength=self.n_local)
            matrix = assemble_cell_matrix(self.mesh, coefficient, diagonal)
            # Jacobi: the matrix is diagonally dominant, and the result does not depend on the partition
            # atol: a velocity error of 1e-15 m/s per cell, so that fluid at rest converges at once
            atol = 1e-15 * float(np.sqrt(self.comm.allreduce(np.sum((self.volume[:self.n_owned] / dt) ** 2))))
            self.momentum.append(CellKSP(self.mesh, matrix, "momentum_", "cg", "jacobi", 1e-8, "momentum",
                                         atol=atol))
        # the pressure's atol, likewise: a flux imbalance of 1e-15 m/s over each cell's faces. At a
        # steady state the right-hand side is round-off, and CG would break down on that noise
        area = self.volume[:self.n_owned] ** (2 / 3)
        self.pressure.set_atol(1e-15 * self.rho / dt * float(np.sqrt(self.comm.allreduce(np.sum(area ** 2)))))
        self._momentum_dt = dt
        self._penalized = False
        self.penalty_rate[:] = 0.0
        return self.momentum

    def _penalize(self, solvers, rhs, penalty):
        """The right-hand side of one momentum solve, with the particles' implicit penalty on the
        matrices' diagonals and in the right-hand side (or, without it, the matrices restored)."""
        if penalty is None and not self._penalized:
            return rhs
        diagonal, target = penalty() if penalty is not None else (np.zeros(self.n_owned), None)
        self.penalty_rate[:self.n_owned] = diagonal / self.volume[:self.n_owned]
        self.mesh.update_ghosts(self.penalty_rate)      # for the Rhie–Chow coefficient of faces to ghosts
        for solver in {id(s): s for s in solvers}.values():   # the components may share one matrix
            solver.add_to_diagonal(diagonal)
        self._penalized = penalty is not None
        if target is None:
            return rhs
        rhs = rhs.copy()
        rhs[:self.n_owned] += target
        return rhs

    # -- discrete operators ------------------------------------------------------------------------
    def interpolate(self, values):
        """Interior face values of a cell field (n_local, ...) by distance weights."""
        return (self.I @ values.reshape(len(values), -1)).reshape((self.n_interior,) + values.shape[1:])

    def gradient(self, values, boundary_values):
        """Gauss gradient of a scalar (n_local,) → (n_local, 3), or of a vector (n_local, 3) →
        (n_local, 3, 3) with [c, i, k] = ∂u_k/∂x_i; ghost rows are made valid."""
        face = np.concatenate([self.interpolate(values), boundary_values])
        S = np.concatenate([self.S, self.S_b])
        if values.ndim == 1:
            grad = (self.D @ (face[:, None] * S)) / self.volume[:, None]
        else:
            grad = np.empty((len(values), 3, values.shape[1]))
            for k in range(values.shape[1]):          # per component: (faces, 3) temporaries, not (faces, 9)
                grad[:, :, k] = self.D @ (face[:, k, None] * S)
            grad /= self.volume[:, None, None]
        return self.mesh.update_ghosts(np.ascontiguousarray(grad))

    def boundary_velocity(self, u):
        """Face velocity on the boundary: fixed (walls, inlets), the cell's (outlets), slip (symmetry)."""
        u_P = u[self.B]
        u_b = np.where(self.dirichlet_u[:, None], self.u_fixed, u_P)
        sym = self.kind == SYMMETRY
        n = self.normal_b[sym]
        u_b[sym] = u_P[sym] - np.einsum("ij,ij->i", u_P[sym], n)[:, None] * n
        return u_b

    def boundary_pressure(self, p):
        """Face pressure on the boundary: fixed on outlets, zero normal gradient elsewhere."""
        return np.where(self.kind == OUTLET, self.p_out, p[self.B])

    def convection_term(self, u, flux, grad_u):
        """Σ_f F_f u_f (n_local, 3): the explicit convection term of the predictor."""
        F = flux[:self.n_interior]
        if self.scheme == "central":
            u_f = self.interpolate(u)
        else:
            # gather the upwind cell only (not both sides and then choose: half the passes and memory)
            forward = F >= 0
            upwind = np.where(forward, self.P, self.N)
            u_f = u[upwind]
            if self.scheme == "linear_upwind":
                r = self.xf - self.mesh.cell_center[upwind]
                for k in range(3):                    # per component: no (faces, 3, 3) gather
                    u_f[:, k] += np.einsum("fi,fi->f", r, grad_u[upwind, :, k])
        F_b = flux[self.n_interior:]
        face = np.concatenate([F[:, None] * u_f, F_b[:, None] * self.boundary_velocity(u)])
        return self.D @ face

    def nonorthogonal(self, grad_f, boundary=None):
        """k_f · (face gradient): the explicit non-orthogonal part of a face-normal gradient term,
        on interior faces or, with a boundary-face mask, on those boundary faces; 0 on orthogonal meshes."""
        if self.orthogonal:
            return 0.0
        k = self.k if boundary is None else self.k_b[boundary]
        return np.einsum("fi,fi->f", k, grad_f)

    # -- the step --------------------------------------------------------------------------------
    def step(self, state: FluidState, dt: float, source=None, patch=None, forcing_iterations: int = 1,
             step: int = 0, time: float = 0.0, penalty=None) -> dict:
        """Collective. Advance ``state`` in place by dt. ``source``: momentum source (n_local, 3) in
        m⁴/s² (force/ρ integrated over the cell), or None. ``patch(u_star, last)``: called (collectively)
        with the predicted velocity, which it may change in its owned rows, ``forcing_iterations``
        times before the projection (``last`` false), then once after it (``last`` true).
        ``penalty()``: called before each of those momentum solves; returns (V κ (n_owned,),
        V κ U (n_owned, 3)) of an implicit penalty κ (U − u) (the particles, ``pmpm.coupling``),
        solved together with the diffusion. Returns diagnostics."""
        rho, nu, V = self.rho, self.nu, self.volume
        u, p, flux = state.u, state.p, state.flux
        momentum_solvers = self._momentum_solvers(dt)  # (re)assembled before the step's temporaries exist
        n_int = self.n_interior

        # 1. predictor
        grad_p = self.gradient(p, self.boundary_pressure(p))
        u_b = self.boundary_velocity(u)
        grad_u = self.gradient(u, u_b) if (self.scheme == "linear_upwind" or not self.orthogonal) else None
        rhs = V[:, None] * u / dt - self.convection_term(u, flux, grad_u) - V[:, None] * grad_p / rho
        # boundary diffusion: Dirichlet values, and the explicit part of the symmetry condition
        dirichlet = nu * self.a_b * self.dirichlet_u
        rhs += np.column_stack([np.bincount(self.B, dirichlet * self.u_fixed[:, k], minlength=self.n_local)
                                for k in range(3)])
        sym = self.kind == SYMMETRY
        if sym.any():
            n = self.normal_b
            u_P = u[self.B]
            off_diagonal = (np.einsum("ij,ij->i", u_P, n)[:, None] - n * u_P) * n   # Σ_{e≠d} n_e u_e n_d
            rhs -= np.column_stack([np.bincount(self.B, np.where(sym, nu * self.a_b * off_diagonal[:, k], 0.0),
                                                minlength=self.n_local) for k in range(3)])
        if not self.orthogonal:  # explicit non-orthogonal part of the diffusion flux
            face = np.einsum("fi,fik->fk", self.k, self.interpolate(grad_u))
            face_b = np.einsum("fi,fik->fk", self.k_b, grad_u[self.B]) * self.dirichlet_u[:, None]
            rhs += nu * (self.D @ np.concatenate([face, face_b]))
        if source is not None:
            rhs += source
        # implicit diffusion; with particles, multi-direct forcing: the patch's momentum becomes a
        # source and the diffusion is solved again, so the rigid motion holds after the solve too
        u_star = u.copy()
        passes = forcing_iterations if patch is not None else 1
        for forcing_pass in range(passes):
            rhs_pass = self._penalize(momentum_solvers, rhs, penalty)
            for k, solver in enumerate(momentum_solvers):
                column = np.ascontiguousarray(u_star[:, k])
                solver.solve(rhs_pass[:, k], column, step, time)
                u_star[:, k] = column
            if patch is not None:  # the particles' direct forcing, before the projection (pmpm.coupling)
                before = u_star[:self.n_owned].copy()
                patch(u_star, False)
                if forcing_pass < passes - 1:
                    rhs[:self.n_owned] += V[:self.n_owned, None] * (u_star[:self.n_owned] - before) / dt
        self.mesh.update_ghosts(u_star)

        # 2. face flux with the Rhie–Chow pressure term. Its coefficient is the predictor's response to a
        # pressure gradient, d = dt/ρ / (1 + κ dt) with the particles' implicit penalty κ: with dt/ρ, a
        # penalized cell's gradient came back into the flux dt/ρ-strong, a pressure diffusion ∝ dt
        # across a particle's surface that lowered its drag as dt grew
        c = dt / rho
        d = c / (1.0 + self.penalty_rate * dt)
        grad_p_f = self.interpolate(grad_p)
        d_f = self.interpolate(d)
        flux_star = np.empty_like(flux)
        flux_star[:n_int] = (np.einsum("fi,fi->f", self.interpolate(u_star + d[:, None] * grad_p), self.S)
                             - d_f * (self.a * (p[self.N] - p[self.P]) + self.nonorthogonal(grad_p_f)))
        outlet = self.kind == OUTLET
        flux_star[n_int:] = self.flux_fixed
        if outlet.any():
            B = self.B[outlet]
            flux_star[n_int:][outlet] = (np.einsum("fi,fi->f", u_star[B] + d[B, None] * grad_p[B], self.S_b[outlet])
                                         - d[B] * (self.a_b[outlet] * (self.p_out[outlet] - p[B])
                                                   + self.nonorthogonal(grad_p[B], outlet)))

        # 3. projection, with non-orthogonal correctors on skewed meshes
        correction = np.zeros(self.n_local)
        divergence = self.D @ flux_star
        extra = np.zeros_like(flux)
        iterations = 0
        for corrector in range(1 + (0 if self.orthogonal else self.correctors)):
            rhs_p = -(divergence - self.D @ extra) / c
            iterations += self.pressure.solve(rhs_p, correction, step, time)
            self.mesh.update_ghosts(correction)
            if not self.orthogonal:
                grad_c = self.gradient(correction, np.where(outlet, 0.0, correction[self.B]))
                extra[:n_int] = c * np.einsum("fi,fi->f", self.k, self.interpolate(grad_c))
        self.last_pressure_iterations = iterations

        # 4. correction
        flux[:] = flux_star - extra
        flux[:n_int] -= c * self.a * (correction[self.N] - correction[self.P])
        if outlet.any():
            flux[n_int:][outlet] -= c * self.a_b[outlet] * (0.0 - correction[self.B[outlet]])
        grad_c = self.gradient(correction, np.where(outlet, 0.0, correction[self.B]))
        # in penalized cells the implicit penalty damps the correction as it damped the predictor's
        # response: without it, each step's p' kicked the fluid inside an accelerating particle
        u[:] = u_star - d[:, None] * grad_c
        if patch is not None:  # the paper's patch after the flow solve: the projection let fluid into the particles
            patch(u, True)
        p += correction
        self.mesh.update_ghosts(u)
        self.mesh.update_ghosts(p)
        return {"pressure_iterations": iterations}

    # -- diagnostics ------------------------------------------------------------------------------
    def cfl(self, state: FluidState, dt: float) -> float:
        """Collective. max over owned cells of dt Σ_f |F_f| / (2 V)."""
        outflow = abs(self.D) @ np.abs(state.flux)
        local = float((dt * outflow[:self.n_owned] / (2 * self.volume[:self.n_owned])).max(initial=0.0))
        return self.comm.allreduce(local, op=MPI.MAX)

    def divergence_norm(self, state: FluidState) -> float:
        """Collective. max over owned cells of |Σ_f F_f| / V (1/s)."""
        div = (self.D @ state.flux)[:self.n_owned] / self.volume[:self.n_owned]
        return self.comm.allreduce(float(np.abs(div).max(initial=0.0)), op=MPI.MAX)

    def boundary_flux(self, state: FluidState) -> dict:
        """Collective. Net outward volume flux (m³/s) through each named boundary."""
        index = self.mesh.face_boundary[self.n_interior:]
        totals = np.bincount(index, state.flux[self.n_interior:], minlength=len(self.mesh.boundary_names))
        totals = self.comm.allreduce(totals, op=MPI.SUM)
        return dict(zip(self.mesh.boundary_names, np.asarray(totals).tolist()))

    def kinetic_energy(self, state: FluidState) -> float:
        """Collective. ½ ρ Σ V |u|² over the owned cells (J)."""
        owned = slice(0, self.n_owned)
        local = 0.5 * self.rho * float(np.sum(self.volume[owned] * np.sum(state.u[owned] ** 2, axis=1)))
        return self.comm.allreduce(local)

    def check(self, state: FluidState, step: int, time: float) -> None:
        """Collective. Raise NumericalError (every rank) when the flow is no longer finite."""
        bad = ~np.isfinite(state.u[:self.n_owned]).all(axis=1)
        where = self.mesh.cell_center[np.argmax(bad)] if bad.any() else None
        found = self.comm.allgather(where)
        for where in found:
            if where is not None:
                raise NumericalError(f"step {step}, t = {time:.6g} s: the flow velocity is not finite in the cell at "
                                     f"({where[0]:.4g}, {where[1]:.4g}, {where[2]:.4g}); reduce [run] dt "
                                     "(see the CFL number printed at start) or use convection = \"upwind\"")

    def destroy(self):
        self.pressure.destroy()
        for solver in self.momentum:
            solver.destroy()


