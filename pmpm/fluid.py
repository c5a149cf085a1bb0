"""Incompressible Navier–Stokes on the distributed mesh: an incremental projection method.

Cell-centred finite volumes, collocated u and p. One step of size dt, in four stages that the
time loop calls in turn (``pmpm.simulation``; particles add implicit terms to stage 2):

1. ``predictor``: the explicit right-hand side V/dt uⁿ − C(uⁿ) − V ∇pⁿ/ρ, the convection C from
   the face flux Fⁿ and an upwind, central or linear-upwind face value;
2. ``solve_momentum``: (V/dt − ν L + D) u* = right-hand side, the diffusion ν L implicit (one KSP
   solve per component, matrices assembled once, at the first step's dt; another dt shifts their
   diagonal), D = V κ an extra diagonal (the particles' implicit penalty κ);
3. ``project``: face flux with a Rhie–Chow-type pressure term, which keeps the pressure free of
   checkerboarding, F* = (u* + d ∇pⁿ)‾·S − d̄ (a_f (pⁿ_N − pⁿ_P) + k_f·∇̄pⁿ) with d = dt/ρ, or
   dt/ρ / (1 + κ dt) in a penalized cell (the predictor's response to a pressure gradient there);
   then the pressure correction p' from Σ a_f (p'_P − p'_N) = −ρ/dt Σ F* (PETSc KSP,
   ``pmpm.pressure``), with explicit non-orthogonal correctors k_f·∇̄p' on skewed meshes;
4. ``correct``: F = F* − dt/ρ (a_f Δp' + k_f·∇̄p'), u = u* − d ∇p', p = pⁿ + p'.

Here a_f = |S|²/(d·S) (over-relaxed split, k_f = S − a_f d) and bars are face interpolations.
The face fluxes F are divergence-free to the KSP tolerance and convect the next step. Each stage
returns new arrays: the state it was given stays as it was.

Gravity: ``p`` is the pressure less the hydrostatic part ρ g·x, so gravity does not appear in the
fluid equations and still fluid stays still; particles feel buoyancy explicitly.

Boundaries: wall (no-slip, moving surface V + Ω × (x − c)), inlet (velocity), outlet (fixed
pressure, zero-gradient velocity), symmetry (no normal flux, free slip).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mpi4py import MPI

from .arrays import csr_matrix
from .errors import NumericalError
from .pressure import CellKSP, PressureSolver, assemble_cell_matrix

WALL, INLET, OUTLET, SYMMETRY = 0, 1, 2, 3
BOUNDARY_CODES = {"wall": WALL, "inlet": INLET, "outlet": OUTLET, "symmetry": SYMMETRY}


@dataclass(frozen=True)
class FluidState:
    """The flow: cell velocity (n_local, 3) m/s, pressure less hydrostatics (n_local,) Pa, face
    volume flux (n_faces,) m³/s. Ghost rows are current."""

    u: np.ndarray
    p: np.ndarray
    flux: np.ndarray


@dataclass(frozen=True)
class Predictor:
    """Stage 1's result: the momentum right-hand side (n_local, 3), m⁴/s² (volume × velocity / time),
    and the pressure gradient ∇pⁿ (n_local, 3), Pa/m, that the projection reuses."""

    rhs: np.ndarray
    grad_p: np.ndarray


@dataclass(frozen=True)
class Projection:
    """Stage 3's result: the face fluxes before the correction (n_faces,), the pressure correction
    p' (n_local,), and the pressure KSP iterations it took."""

    flux: np.ndarray
    correction: np.ndarray
    iterations: int


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
        self._momentum = []          # the momentum KSPs, assembled at the first step
        self._momentum_dt = None     # the dt they were assembled for
        self._atol_dt = None

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
        self.D = csr_matrix(vals, rows, cols, (self.n_local, n_faces))
        self.D_abs = abs(self.D)[:self.n_owned]                   # Σ over an owned cell's faces of |·|
        # interior face interpolation as a matrix: one sparse product is 3× faster than two gathers
        faces = np.arange(n_int)
        self.I = csr_matrix(np.concatenate([self.w, 1 - self.w]), np.concatenate([faces, faces]),
                            np.concatenate([self.P, self.N]), (n_int, self.n_local))
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

    def _momentum_solvers(self, dt: float) -> list:
        """The implicit-diffusion KSPs (V/dt₀ − ν L) of the three components, assembled once, at the
        first step's dt₀ (another dt shifts their diagonal: ``solve_momentum``); their atol and the
        pressure's set for this dt."""
        if not self._momentum:
            self._momentum_dt = float(dt)
            self._momentum = self._assemble_momentum(dt)
        if self._atol_dt != dt:
            # a flux imbalance of 1e-15 m/s over each cell's faces: at a steady state the pressure's
            # right-hand side is round-off, and CG would break down on that noise
            area = self.volume[:self.n_owned] ** (2 / 3)
            self.pressure.set_atol(1e-15 * self.rho / dt * float(np.sqrt(self.comm.allreduce(np.sum(area ** 2)))))
            # a velocity error of 1e-15 m/s per cell, so that fluid at rest converges at once
            atol = 1e-15 * float(np.sqrt(self.comm.allreduce(np.sum((self.volume[:self.n_owned] / dt) ** 2))))
            for solver in {id(s): s for s in self._momentum}.values():
                solver.set_atol(atol)
            self._atol_dt = dt
        return self._momentum

    @property
    def momentum(self) -> list:
        """The momentum KSPs (one per velocity component, possibly one shared)."""
        return self._momentum

    def _assemble_momentum(self, dt: float) -> list:
        nu = self.nu
        coefficient = np.concatenate([nu * self.a, np.zeros(len(self.a_b))])
        solvers = []
        # the three matrices differ only on symmetry faces: without them, one matrix and KSP serve all
        symmetry = self.comm.allreduce(bool((self.kind == SYMMETRY).any()), op=MPI.LOR)
        for component in range(3):
            if component and not symmetry:
                solvers.append(solvers[0])
                continue
            boundary = nu * self.a_b * np.where(self.dirichlet_u, 1.0, 0.0)
            boundary += nu * self.a_b * np.where(self.kind == SYMMETRY, self.normal_b[:, component] ** 2, 0.0)
            diagonal = self.volume / dt + np.bincount(self.B, boundary, minlength=self.n_local)
            matrix = assemble_cell_matrix(self.mesh, coefficient, diagonal)
            # Jacobi: the matrix is diagonally dominant, and the result does not depend on the partition
            solvers.append(CellKSP(self.mesh, matrix, "momentum_", "cg", "jacobi", 1e-8, "momentum"))
        return solvers

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

    # -- the step's stages ----------------------------------------------------------------------
    def predictor(self, state: FluidState, dt: float) -> Predictor:
        """Collective. The right-hand side of the momentum predictor (stage 1), everything explicit:
        V/dt uⁿ − C(uⁿ) − V ∇pⁿ/ρ, the boundary diffusion terms and the non-orthogonal correction."""
        rho, nu, V = self.rho, self.nu, self.volume
        u, p, flux = state.u, state.p, state.flux
        self._momentum_solvers(dt)   # assembled (the first step) before the step's temporaries exist
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
        return Predictor(rhs, grad_p)

    def solve_momentum(self, rhs: np.ndarray, guess: np.ndarray, dt: float, step: int = 0, time: float = 0.0,
                       extra_diagonal: np.ndarray | None = None) -> np.ndarray:
        """Collective. The implicit diffusion (stage 2): (V/dt − ν L + D) u* = rhs, one KSP solve per
        component, from ``guess`` (n_local, 3). ``extra_diagonal`` (n_owned,) D, e.g. the particles'
        penalty V κ (``pmpm.coupling``), replaces any earlier one; None solves without. Returns a new
        (n_local, 3) array: owned rows solved, ghost rows those of ``guess`` (``project`` refreshes them)."""
        solvers = self._momentum_solvers(dt)
        # the matrices were assembled for dt₀: V/dt on the diagonal is V/dt₀ + V (1/dt − 1/dt₀)
        shift = None if dt == self._momentum_dt else self.volume[:self.n_owned] * (1.0 / dt - 1.0 / self._momentum_dt)
        if extra_diagonal is not None:
            shift = extra_diagonal[:self.n_owned] if shift is None else shift + extra_diagonal[:self.n_owned]
        for solver in {id(s): s for s in solvers}.values():   # the components may share one matrix
            solver.set_extra_diagonal(shift)
        u_star = guess.copy()
        for k, solver in enumerate(solvers):
            column = np.ascontiguousarray(u_star[:, k])
            solver.solve(rhs[:, k], column, step, time)
            u_star[:, k] = column
        return u_star

    def project(self, state: FluidState, u_star: np.ndarray, predicted: Predictor, dt: float, step: int = 0,
                time: float = 0.0, volume_source: np.ndarray | None = None,
                penalty_rate: np.ndarray | None = None) -> Projection:
        """Collective. Face fluxes with the Rhie–Chow pressure term, then the pressure correction p'
        that makes them divergence-free (stage 3; non-orthogonal correctors on skewed meshes), or,
        with ``volume_source`` (n_local,) q in m³/s, makes each cell's net outflow q (the fluid that
        new particles displace). ``penalty_rate`` (n_local,) κ (1/s) of the implicit penalty of the
        last momentum solve, ghost rows current, or None. Refreshes ``u_star``'s ghost rows first
        (in place)."""
        rho, n_int = self.rho, self.n_interior
        self.mesh.update_ghosts(u_star)
        p, grad_p = state.p, predicted.grad_p
        c = dt / rho
        grad_p_f = self.interpolate(grad_p)
        flux_star = np.empty_like(state.flux)
        outlet = self.kind == OUTLET
        B = self.B[outlet]
        if penalty_rate is None:
            flux_star[:n_int] = (np.einsum("fi,fi->f", self.interpolate(u_star) + c * grad_p_f, self.S)
                                 - c * (self.a * (p[self.N] - p[self.P]) + self.nonorthogonal(grad_p_f)))
            d_b = c
        else:
            # the Rhie–Chow coefficient is the predictor's response to a pressure gradient,
            # d = dt/ρ / (1 + κ dt): with dt/ρ a penalized cell's gradient came back into the flux
            # dt/ρ-strong, a pressure diffusion ∝ dt across a particle's surface that lowered its drag
            d = c / (1.0 + penalty_rate * dt)
            flux_star[:n_int] = (np.einsum("fi,fi->f", self.interpolate(u_star + d[:, None] * grad_p), self.S)
                                 - self.interpolate(d) * (self.a * (p[self.N] - p[self.P])
                                                          + self.nonorthogonal(grad_p_f)))
            d_b = d[B]
        flux_star[n_int:] = self.flux_fixed
        if outlet.any():
            flux_star[n_int:][outlet] = (np.einsum("fi,fi->f", u_star[B] + np.reshape(d_b, (-1, 1)) * grad_p[B],
                                                   self.S_b[outlet])
                                         - d_b * (self.a_b[outlet] * (self.p_out[outlet] - p[B])
                                                  + self.nonorthogonal(grad_p[B], outlet)))
        correction = np.zeros(self.n_local)
        divergence = self.D @ flux_star
        if volume_source is not None:
            divergence -= volume_source
        extra = np.zeros_like(flux_star)
        iterations = 0
        for corrector in range(1 + (0 if self.orthogonal else self.correctors)):
            rhs_p = -(divergence - self.D @ extra) / c
            iterations += self.pressure.solve(rhs_p, correction, step, time)
            self.mesh.update_ghosts(correction)
            if not self.orthogonal:
                grad_c = self.gradient(correction, np.where(outlet, 0.0, correction[self.B]))
                extra[:n_int] = c * np.einsum("fi,fi->f", self.k, self.interpolate(grad_c))
        return Projection(flux_star - extra, correction, iterations)

    def correct(self, state: FluidState, u_star: np.ndarray, projection: Projection, dt: float,
                penalty_rate: np.ndarray | None = None) -> FluidState:
        """Collective. The new flow (stage 4): F = F* − dt/ρ (a_f Δp' + k_f·∇̄p'), u = u* − d ∇p',
        p = pⁿ + p', ghost rows current; d = dt/ρ, or dt/ρ / (1 + κ dt) where ``penalty_rate`` κ
        (n_local,) penalizes a cell: the implicit penalty damps the correction as it damped the
        predictor's response (undamped, each step's p' kicked the fluid inside an accelerating
        particle)."""
        c, n_int = dt / self.rho, self.n_interior
        correction = projection.correction
        outlet = self.kind == OUTLET
        flux = projection.flux.copy()
        flux[:n_int] -= c * self.a * (correction[self.N] - correction[self.P])
        if outlet.any():
            flux[n_int:][outlet] -= c * self.a_b[outlet] * (0.0 - correction[self.B[outlet]])
        grad_c = self.gradient(correction, np.where(outlet, 0.0, correction[self.B]))
        if penalty_rate is None:
            u = u_star - c * grad_c
        else:
            u = u_star - (c / (1.0 + penalty_rate * dt))[:, None] * grad_c
        p = state.p + correction
        self.mesh.update_ghosts(u)
        self.mesh.update_ghosts(p)
        return FluidState(u, p, flux)

    def step(self, state: FluidState, dt: float, step: int = 0, time: float = 0.0) -> FluidState:
        """Collective. One step of the flow alone (no particles): the four stages in order."""
        predicted = self.predictor(state, dt)
        u_star = self.solve_momentum(predicted.rhs, state.u, dt, step, time)
        projection = self.project(state, u_star, predicted, dt, step, time)
        return self.correct(state, u_star, projection, dt)

    # -- diagnostics ------------------------------------------------------------------------------
    def cfl(self, state: FluidState, dt: float) -> float:
        """Collective. The CFL number: max over owned cells of dt Σ_f |F_f| / (2 V)."""
        return self.largest_cfl(state, dt)[0]

    def boundary_cfl(self, dt: float) -> float:
        """Collective. The CFL number the boundary velocities give: their largest speed × dt over the
        smallest cell size."""
        speed = float(np.linalg.norm(self.u_fixed, axis=1).max(initial=0.0))
        return self.comm.allreduce(speed * dt / float(self.h.min(initial=np.inf)), op=MPI.MAX)

    def largest_cfl(self, state: FluidState, dt: float) -> tuple[float, np.ndarray | None]:
        """Collective. The CFL number and the centre (3,) of the cell where it is reached (None
        without cells), the same on every rank."""
        per_cell = dt * self.convective_rates(state)
        worst = int(np.argmax(per_cell)) if len(per_cell) else -1
        mine = (float(per_cell[worst]), self.mesh.cell_center[worst]) if worst >= 0 else (-1.0, None)
        if self.comm.size == 1:
            return mine
        return max(self.comm.allgather(mine), key=lambda pair: pair[0])

    def convective_rates(self, state: FluidState) -> np.ndarray:
        """Local. Σ_f |F_f| / (2 V) of each owned cell (1/s): its CFL number per second of dt
        (not finite values as infinity)."""
        rates = (self.D_abs @ np.abs(state.flux)) / (2 * self.volume[:self.n_owned])
        return np.where(np.isnan(rates), np.inf, rates)

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
        for solver in {id(s): s for s in self._momentum}.values():
            solver.destroy()


