"""The cell KSPs (pmpm/pressure.py): a failed solve says what to change."""
import numpy as np
import pytest
from mpi4py import MPI

from pmpm.errors import NumericalError
from pmpm.mesh import Mesh
from pmpm.pressure import CellKSP, assemble_cell_matrix


def test_failed_momentum_solve_advises_the_time_step_first():
    """V/dt − ν L is diagonally dominant: a momentum solve fails only on a blown-up right-hand
    side, which a smaller dt cures and another preconditioner does not."""
    mesh = Mesh.from_box(MPI.COMM_SELF, [0, 0, 0], [1, 1, 1], [3, 3, 3])
    face_coefficient = np.full(len(mesh.face_cells), 0.1)
    matrix = assemble_cell_matrix(mesh, face_coefficient, mesh.cell_volume / 0.01)
    solver = CellKSP(mesh, matrix, "momentum_", "cg", "jacobi", 1e-8, "momentum")
    rhs = np.ones(mesh.n_local_cells)
    rhs[4] = np.inf
    try:
        with pytest.raises(NumericalError) as error:
            solver.solve(rhs, np.zeros(mesh.n_local_cells), step=7, time=0.07)
    finally:
        solver.destroy()
    message = str(error.value)
    assert message.startswith("the momentum solve did not converge at step 7, t = 0.07 s")
    assert "reduce [run] dt first" in message
    assert message.index("reduce [run] dt") < message.index("-momentum_pc_type")
