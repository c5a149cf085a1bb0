"""Flow validation cases shared by tests/test_flow.py and bench/flow.py.

Each function builds a mesh and a :class:`pmpm.fluid.FlowSolver` from plain arguments (no case
file), runs it and returns numbers to compare with a reference. Run as a script it is the
2-rank half of the 1-vs-2-rank test:

    mpirun -n 2 python tests/flow_cases.py cavity OUT.npy [N]

writes the cavity fields (u, p of the owned cells, in serial cell order) gathered on rank 0.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from mpi4py import MPI

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pmpm.case import Section, check_table  # noqa: E402
from pmpm.schema import SCHEMA  # noqa: E402
from pmpm.fluid import FlowSolver  # noqa: E402
from pmpm.mesh import Mesh  # noqa: E402

# Ghia, Ghia & Shin (1982), Table I, Re = 100: u on the vertical centreline x = 0.5
GHIA_Y = np.array([1.0, .9766, .9688, .9609, .9531, .8516, .7344, .6172, .5, .4531, .2813, .1719, .1016,
                   .0703, .0625, .0547, 0.0])
GHIA_U = np.array([1.0, .84123, .78871, .73722, .68717, .23151, .00332, -.13641, -.20581, -.21090, -.15662,
                   -.10150, -.06434, -.04775, -.04192, -.03717, 0.0])


def fluid(**values) -> Section:
    """A checked [fluid] section (density 1, viscosity 0.01 unless given)."""
    values = {"density": 1.0, "viscosity": 0.01, **values}
    return Section(check_table(values, SCHEMA["fluid"], "fluid", "test"))


def boundary(**values) -> Section:
    """A checked [boundary.<name>] section."""
    return Section(check_table(values, SCHEMA["boundary.*"], "boundary", "test"))


SLAB = {"zmin": boundary(type="symmetry"), "zmax": boundary(type="symmetry")}


def cavity_solver(comm, n: int, cell_type: str = "hex", re: float = 100.0, depth: float | None = None,
                  **fluid_values):
    """2-D lid-driven cavity: unit square, n × n × 1 cells, lid ymax at u = 1, symmetry front/back."""
    depth = 1.0 / n if depth is None else depth
    mesh = Mesh.from_box(comm, (0, 0, 0), (1, 1, depth), (n, n, 1), cell_type)
    bounds = {"ymax": boundary(type="wall", velocity=[1.0, 0.0, 0.0]), **SLAB}
    return FlowSolver(mesh, fluid(viscosity=1.0 / re, **fluid_values), bounds)


def run(solver, dt: float, steps: int, state=None):
    state = solver.initial_state() if state is None else state
    for n in range(steps):
        state = solver.step(state, dt, step=n, time=n * dt)
    return state


def owned(solver, values):
    return values[:solver.mesh.n_owned_cells]


def gather_serial(mesh, values):
    """Collective. Owned rows of ``values`` on every rank, in serial (rank-independent) cell order."""
    n = mesh.n_owned_cells
    parts = mesh.comm.allgather((mesh.cell_serial[:n], np.asarray(values)[:n]))
    serial = np.concatenate([s for s, _ in parts])
    data = np.concatenate([v for _, v in parts])
    out = np.empty_like(data)
    out[serial] = data
    return out


def centreline_u(solver, state, ys):
    """Collective. u_x at (0.5, y) for each y: the value of the cell holding the point plus the
    cell gradient times the offset (second order on any cell shape), averaged over the cells that
    hold the four points (0.5 ± ε, y ± ε), so that a point on a face takes both sides (the answer
    does not depend on which cell point location picks). Walls give 0 and 1 exactly."""
    mesh = solver.mesh
    z = mesh.vertex_xyz[:, 2]
    zmid = 0.5 * (mesh.comm.allreduce(float(z.min()), op=MPI.MIN) + mesh.comm.allreduce(float(z.max()), op=MPI.MAX))
    exact = np.column_stack([np.full(len(ys), 0.5), np.clip(ys, 1e-6, 1 - 1e-6), np.full(len(ys), zmid)])
    grad = solver.gradient(state.u, solver.boundary_velocity(state.u))
    local = np.zeros(len(ys))
    hit = np.zeros(len(ys))
    for dx, dy in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
        cells = mesh.find_owned_cells(exact + 1e-7 * np.array([dx, dy, 0.0]))
        mine = cells >= 0
        c = cells[mine]
        local[mine] += state.u[c, 0] + np.einsum("ij,ij->i", exact[mine] - mesh.cell_center[c], grad[c, :, 0])
        hit[mine] += 1
    total = mesh.comm.allreduce(local)
    count = mesh.comm.allreduce(hit)
    values = total / np.maximum(count, 1)
    values[ys <= 0] = 0.0
    values[ys >= 1] = 1.0
    return values


def ghia_deviation(solver, state) -> float:
    """Collective. max |u(0.5, y) − Ghia| over Ghia's 17 points, in units of the lid speed."""
    return float(np.abs(centreline_u(solver, state, GHIA_Y) - GHIA_U).max())


def cavity_fields(comm, n: int = 12, steps: int = 20, dt: float = 0.05, cell_type: str = "hex"):
    """Collective. (u, p) of the owned cells after ``steps`` cavity steps, serial order (tight tolerances)."""
    solver = cavity_solver(comm, n, cell_type, pressure_rtol=1e-13)
    state = run(solver, dt, steps)
    u = gather_serial(solver.mesh, state.u)
    p = gather_serial(solver.mesh, state.p)
    solver.destroy()
    return u, p


if __name__ == "__main__":
    what, out = sys.argv[1], Path(sys.argv[2])
    if what == "cavity":
        n = int(sys.argv[3]) if len(sys.argv) > 3 else 12
        cell_type = sys.argv[4] if len(sys.argv) > 4 else "hex"
        u, p = cavity_fields(MPI.COMM_WORLD, n, cell_type=cell_type)
        if MPI.COMM_WORLD.rank == 0:
            np.savez(out, u=u, p=p, ranks=MPI.COMM_WORLD.size)
    else:
        raise SystemExit(f"unknown case {what}")
