"""The pressure Poisson equation of the projection step, solved with PETSc KSP.

The projection (``pmpm.fluid``) asks for the pressure p (Pa) whose compact face gradient makes the
face fluxes divergence-free:

    Σ_f a_f (p_P − p_N)  +  Σ_outlet a_b (p_P − p_b)  =  b_P,       a_f = |S_f|² / (d_f · S_f)  (m)

(the over-relaxed orthogonal part of ∇p·S on face f; d_f joins the two cell centres, or the cell
centre to the face centre on the boundary). The matrix is symmetric positive (semi-)definite,
depends on the mesh only, and is therefore assembled once, as a distributed PETSc AIJ whose rows
are the owned cells (row = ``mesh.cell_gid``), together with its AMG hierarchy (``ksp.setUp`` once).

Solver: CG preconditioned with algebraic multigrid (default ``ml``, see docs/flow.md for the
measurements against ``gamg`` and ``hypre``), unpreconditioned residual norm so that
``‖b − A p‖ ≤ rtol ‖b‖`` is what "converged" means, initial guess = the previous pressure. Every
choice can be overridden from the command line under the options prefix ``pressure_``
(``-pressure_ksp_type``, ``-pressure_pc_type``, ``-pressure_ksp_rtol`` …). Without a Dirichlet
(outlet) face the problem is pure Neumann: the constant null space is attached to the matrix
(and as near null space for the AMG) and removed from every right-hand side.
"""
from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from .arrays import csr_matrix
from .errors import NumericalError

DEFAULT_PC = "ml"
# PETSc options for the default preconditioner, unless the command line sets them: one SOR sweep per
# level instead of two (64³ cavity: 11 CG iterations instead of 9, but 0.19 s per solve instead of 0.28)
PC_DEFAULTS = {"ml": {"mg_levels_ksp_max_it": "1", "pc_ml_maxCoarseSize": "500"}}
_REASONS = {getattr(PETSc.KSP.ConvergedReason, name): name for name in dir(PETSc.KSP.ConvergedReason)
            if name.isupper()}


def ksp_reason_name(reason: int) -> str:
    """PETSc's name of a KSP converged/diverged reason (``DIVERGED_ITS`` …)."""
    return _REASONS.get(int(reason), str(int(reason)))


def assemble_cell_matrix(mesh, face_coefficient: np.ndarray, diagonal: np.ndarray) -> PETSc.Mat:
    """Collective. The distributed matrix ``Σ_f c_f (x_P − x_N) + diag_P x_P`` over the owned cells.

    Parameters
    ----------
    mesh : pmpm.mesh.Mesh
    face_coefficient : (n_faces,) float
        c_f ≥ 0 of each face (ignored on boundary faces, whose share goes into ``diagonal``).
    diagonal : (n_local_cells,) float
        Extra diagonal of each cell (boundary conditions, V/dt); only owned rows are read.

    Returns
    -------
    PETSc.Mat
        AIJ, rows and columns in ``mesh.cell_gid`` numbering; the caller owns (destroys) it.

    Notes
    -----
    Each rank builds its owned rows as a scipy CSR with global column numbers (duplicates summed,
    columns sorted) and hands it to ``createAIJ(csr=...)``: one vectorised pass, no per-entry call.
    A face between an owned and a ghost cell is held by both ranks; each fills only its own row.
    """
    n_owned = mesh.n_owned_cells
    owner, neighbour = mesh.face_cells[:, 0], mesh.face_cells[:, 1]
    interior = neighbour >= 0
    c = face_coefficient[interior]
    p, n = owner[interior], neighbour[interior]
    gid = mesh.cell_gid
    rows, cols, vals = [], [], []
    for row_cell, col_cell in ((p, n), (n, p)):
        mine = row_cell < n_owned
        rows += [row_cell[mine], row_cell[mine]]
        cols += [gid[row_cell[mine]], gid[col_cell[mine]]]
        vals += [c[mine], -c[mine]]
    rows.append(np.arange(n_owned))
    cols.append(gid[:n_owned])
    vals.append(np.asarray(diagonal[:n_owned], dtype=float))
    rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    n_global = mesh.n_global_cells
    csr = csr_matrix(vals, rows, cols, (n_owned, n_global))
    csr.sum_duplicates()
    csr.sort_indices()
    matrix = PETSc.Mat().createAIJ(size=((n_owned, n_global), (n_owned, n_global)),
                                   csr=(csr.indptr.astype(PETSc.IntType), csr.indices.astype(PETSc.IntType),
                                        csr.data), comm=mesh.comm)
    matrix.assemble()
    return matrix


class CellKSP:
    """A KSP on one cell-centred matrix, with numpy in/out on the owned cells. Owns its PETSc objects.

    Parameters
    ----------
    mesh : pmpm.mesh.Mesh
    matrix : PETSc.Mat
        Taken over: destroyed with this object.
    prefix : str
        PETSc options prefix, e.g. ``"pressure_"``.
    ksp_type, pc_type : str
        Defaults, applied before ``setFromOptions`` so that the command line wins.
    rtol : float
        Relative tolerance on the unpreconditioned residual, relative to ‖b‖.
    what : str
        Name used in error messages ("pressure", "momentum").
    """

    def __init__(self, mesh, matrix, prefix: str, ksp_type: str, pc_type: str, rtol: float, what: str,
                 null_space: bool = False, atol: float = 0.0):
        self.mesh, self.comm, self.what = mesh, mesh.comm, what
        self.n_owned = mesh.n_owned_cells
        self.matrix = matrix
        self.null_space = None
        if null_space:
            self.null_space = PETSc.NullSpace().create(constant=True, comm=self.comm)
            matrix.setNullSpace(self.null_space)
            matrix.setNearNullSpace(self.null_space)
        self._x_array = np.zeros(self.n_owned)
        self._b_array = np.zeros(self.n_owned)
        sizes = (self.n_owned, mesh.n_global_cells)
        self._x = PETSc.Vec().createWithArray(self._x_array, size=sizes, comm=self.comm)
        self._b = PETSc.Vec().createWithArray(self._b_array, size=sizes, comm=self.comm)
        options = PETSc.Options(prefix)
        for key, value in PC_DEFAULTS.get(options.getString("pc_type", pc_type), {}).items():
            if not options.hasName(key):
                options.setValue(key, value)
        ksp = PETSc.KSP().create(comm=self.comm)
        ksp.setOptionsPrefix(prefix)
        ksp.setOperators(matrix)
        ksp.setType(ksp_type)
        ksp.getPC().setType(pc_type)
        ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
        # no divergence test: a warm start may be far above a tiny right-hand side (fluid at rest)
        ksp.setTolerances(rtol=rtol, atol=atol, divtol=1e300, max_it=1000)
        ksp.setInitialGuessNonzero(True)
        ksp.setFromOptions()
        ksp.setUp()
        self.ksp = ksp
        self.iterations = 0  # of the last solve
        self.total_iterations = 0
        self._base_diagonal = None   # the matrix's own diagonal, kept while an addition is in place

    def set_extra_diagonal(self, extra: np.ndarray | None) -> None:
        """Collective. Set the diagonal to the assembled one plus ``extra`` (n_owned,), replacing any
        earlier addition (the particles' penalty, which changes every step); None restores the
        assembled diagonal. PETSc sees the matrix state change, so the preconditioner is set up
        again at the next solve."""
        if extra is None and self._base_diagonal is None:
            return
        if self._base_diagonal is None:
            assembled = self.matrix.getDiagonal()
            self._base_diagonal = assembled.getArray().copy()
            assembled.destroy()
        values = self._base_diagonal if extra is None else self._base_diagonal + extra[:self.n_owned]
        diagonal = PETSc.Vec().createWithArray(values, size=(self.n_owned, self.mesh.n_global_cells), comm=self.comm)
        self.matrix.setDiagonal(diagonal, addv=PETSc.InsertMode.INSERT_VALUES)
        diagonal.destroy()
        if extra is None:
            self._base_diagonal = None

    def set_atol(self, atol: float) -> None:
        """The absolute tolerance on ‖b − A x‖, the other tolerances kept."""
        rtol, _, divtol, max_it = self.ksp.getTolerances()
        self.ksp.setTolerances(rtol=rtol, atol=atol, divtol=divtol, max_it=max_it)

    def _written(self) -> None:
        """Tell PETSc that the numpy arrays under b and x were written: PETSc caches a vector's norm
        until its state changes, and writes through numpy do not change it, so without this KSP
        would measure rtol against ‖b‖ of an earlier solve."""
        self._b.stateIncrease()
        self._x.stateIncrease()

    def solve(self, rhs: np.ndarray, solution: np.ndarray, step: int = 0, time: float = 0.0) -> int:
        """Collective. Solve A x = rhs; ``solution[:n_owned]`` is the initial guess and receives x.

        Parameters
        ----------
        rhs : (n_owned,) or longer float; only the owned rows are read.
        solution : (n_local,) float, updated in place on the owned rows (ghost rows untouched).
        step, time : for the error message.

        Returns
        -------
        int : iterations taken.

        Raises
        ------
        NumericalError
            When the KSP diverges, naming PETSc's reason, the step and the time.
        """
        self._b_array[:] = rhs[:self.n_owned]
        self._x_array[:] = solution[:self.n_owned]
        self._written()
        if self.null_space is not None:
            self.null_space.remove(self._b)
        self.ksp.solve(self._b, self._x)
        reason = self.ksp.getConvergedReason()
        self.iterations = self.ksp.getIterationNumber()
        self.total_iterations += self.iterations
        if reason < 0:
            raise NumericalError(
                f"the {self.what} solve did not converge at step {step}, t = {time:.6g} s: KSP "
                f"{ksp_reason_name(reason)} after {self.iterations} iterations (residual "
                f"{self.ksp.getResidualNorm():.3g}, |b| {self._b.norm():.3g}); {self._advice()}")
        solution[:self.n_owned] = self._x_array
        return self.iterations

    def _advice(self) -> str:
        """What to change after a failed solve. The momentum matrix V/dt − ν L is diagonally dominant:
        CG + Jacobi fails on it only when its right-hand side has blown up, i.e. the time step."""
        prefix = self.ksp.getOptionsPrefix()
        if self.what == "momentum":
            return (f"the flow is likely unstable at this time step: reduce [run] dt first (the CFL number "
                    f"should stay below 1); a -{prefix}pc_type is seldom the cause")
        return f"reduce [run] dt or try another -{prefix}pc_type"

    def residual_norm(self, rhs: np.ndarray, solution: np.ndarray) -> tuple[float, float]:
        """Collective. (‖b − A x‖, ‖b‖) over all ranks, null space removed from b."""
        self._b_array[:] = rhs[:self.n_owned]
        self._x_array[:] = solution[:self.n_owned]
        self._written()
        if self.null_space is not None:
            self.null_space.remove(self._b)
        r = self._b.duplicate()
        self.matrix.mult(self._x, r)
        r.aypx(-1.0, self._b)
        norms = r.norm(), self._b.norm()
        r.destroy()
        return norms

    def destroy(self) -> None:
        """Free the PETSc objects (collective)."""
        for obj in (self.ksp, self._x, self._b, self.matrix, self.null_space):
            if obj is not None:
                obj.destroy()
        self.ksp = self._x = self._b = self.matrix = self.null_space = None


class PressureSolver(CellKSP):
    """The pressure Poisson matrix of a mesh and its CG + AMG solver, set up once.

    Parameters
    ----------
    mesh : pmpm.mesh.Mesh
    face_coefficient : (n_faces,) float
        a_f = |S|²/(d·S) (m) of every face; on boundary faces it is used only where ``dirichlet``.
    dirichlet : (n_faces,) bool
        Boundary faces with a fixed pressure (outlets). None anywhere on the mesh → pure Neumann,
        the constant null space is attached.
    rtol : float
        Relative tolerance of the unpreconditioned residual (``[fluid] pressure_rtol``).
    pc_type : str
        Default preconditioner (``-pressure_pc_type`` overrides it).

    Notes
    -----
    ``solve(rhs, p)`` takes ``b`` of the equation in the module docstring with the outlet terms
    ``a_b p_b`` already included (see ``dirichlet_rhs``).
    """

    def __init__(self, mesh, face_coefficient: np.ndarray, dirichlet: np.ndarray, *, rtol: float = 1e-8,
                 pc_type: str = DEFAULT_PC, ksp_type: str = "cg", prefix: str = "pressure_"):
        n_local = mesh.n_local_cells
        owner = mesh.face_cells[:, 0]
        self.dirichlet_faces = np.flatnonzero(dirichlet)
        diagonal = np.bincount(owner[self.dirichlet_faces], face_coefficient[self.dirichlet_faces],
                               minlength=n_local)
        has_dirichlet = mesh.comm.allreduce(int(self.dirichlet_faces.size)) > 0
        matrix = assemble_cell_matrix(mesh, face_coefficient, diagonal)
        super().__init__(mesh, matrix, prefix, ksp_type, pc_type, rtol, "pressure",
                         null_space=not has_dirichlet)
        self.pure_neumann = not has_dirichlet
