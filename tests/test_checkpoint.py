"""checkpoint.h5 holds the whole run state: a run restored from it on the same ranks continues
bit for bit as the uninterrupted run, flow, coupling memory, contact memory and moving walls
included."""
from dataclasses import fields

import numpy as np
import pytest
from mpi4py import MPI

from pmpm import checkpoint
from pmpm.ownership import gather
from pmpm.case import load_case
from pmpm.simulation import Simulation, build_mesh

SETTLING = """
[run]
end_time = 1.0
dt = 0.004
gravity = [0.3, 0.0, -9.81]
[mesh]
box = { lower = [0, 0, 0], upper = [0.06, 0.06, 0.1], cells = [10, 10, 16] }
[fluid]
density = 1000.0
viscosity = 0.1
[coupling]
volume_fraction = "subcell"
[[particles.add]]
position = [0.029, 0.031, 0.06]
radius = 0.008
density = 2000.0
"""

BED = """
[run]
end_time = 1.0
dt = 0.001
[mesh]
box = { lower = [0, 0, 0], upper = [0.2, 0.2, 0.2], cells = [4, 4, 4] }
[boundary.zmax]
type = "wall"
motion = "rigid"
velocity = [0.0, 0.0, -0.5]
[collisions]
restitution = 0.5
friction = 0.5
[particles]
file = "bed.txt"
"""


def build(comm, tmp_path, text, name, extra=None):
    folder = tmp_path / name
    if comm.rank == 0:
        folder.mkdir(exist_ok=True)
        (folder / "case.toml").write_text(text)
        if extra:
            for file, content in extra.items():
                (folder / file).write_text(content)
    comm.Barrier()
    case = load_case(folder / "case.toml", [])
    return case, build_mesh(comm, case), folder


def assert_same_state(a, b, exact: bool, comm=None):
    """Every array of two run states equal: bit for bit, or to round-off (relative 1e-9). Where ranks
    own particles (collective, ``comm``), the coupling memory of every rank, gathered."""
    def same(x, y, what):
        x, y = np.asarray(x), np.asarray(y)
        assert x.shape == y.shape, what
        if exact:
            np.testing.assert_array_equal(x, y, err_msg=what)
        else:
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9 * (np.abs(x).max(initial=0) + 1e-300), err_msg=what)
    assert (a.time, a.step, a.next_id, a.removed, a.releases) == (b.time, b.step, b.next_id, b.removed, b.releases)
    for f in fields(a.particles):
        same(getattr(a.particles, f.name), getattr(b.particles, f.name), f.name)
    same(a.hydro_force, b.hydro_force, "hydro_force")
    if a.fluid is not None:
        for name in ("u", "p", "flux"):
            same(getattr(a.fluid, name), getattr(b.fluid, name), name)
        memory_a, memory_b = a.coupling, b.coupling
        if a.partition is not None:   # each rank remembers the particles it held
            memory_a, memory_b = memory_a.gathered(comm), memory_b.gathered(comm)
        for name, values in memory_a.to_arrays().items():
            same(values, memory_b.to_arrays()[name], name)
    if a.walls is not None:
        for name in ("a", "b", "c", "normal", "center"):
            same(getattr(a.walls, name), getattr(b.walls, name), name)
    if a.contacts is not None:
        for name, values in a.contacts.to_arrays().items():
            same(values, b.contacts.to_arrays()[name], name)


def continue_from_checkpoint(comm, case, mesh, folder, steps, dt):
    """Run 2 × steps; separately, run ``steps``, write and read a checkpoint, restore it into a fresh
    simulation and run ``steps`` more. Returns both end states."""
    whole = Simulation(comm, case, mesh, quiet=True)
    for _ in range(2 * steps):
        whole.advance(dt)
    half = Simulation(comm, case, mesh, quiet=True)
    for _ in range(steps):
        half.advance(dt)
    checkpoint.write(comm, folder, mesh, half.state)
    rest = Simulation(comm, case, mesh, quiet=True)
    rest.state = checkpoint.restore(comm, checkpoint.read(comm, folder / "checkpoint.h5"), rest.model, rest.state,
                                    folder / "checkpoint.h5")
    assert_same_state(half.state, rest.state, exact=True, comm=comm)
    for _ in range(steps):
        rest.advance(dt)
    return whole.state, rest.state


@pytest.fixture
def reproducible_pressure_pc():
    """The ML preconditioner's setup differs from one instance to the next within a process (a
    relative 1e-7 in a first solve; a restarted process builds the same one again): the runs
    compared here in one process use GAMG, whose setup is reproducible."""
    from petsc4py import PETSc
    PETSc.Options().setValue("pressure_pc_type", "gamg")
    yield
    PETSc.Options().delValue("pressure_pc_type")


@pytest.mark.mpi
def test_restart_continues_a_coupled_run(comm, shared_tmp, reproducible_pressure_pc):
    """A heavy sphere settling across the rank boundary, 2 × 6 steps against 6, checkpoint, 6: the
    same particle, flow and coupling memory, bit for bit."""
    case, mesh, folder = build(comm, shared_tmp, SETTLING, "settling")
    whole, rest = continue_from_checkpoint(comm, case, mesh, folder, 6, case.run.dt)
    assert gather(comm, whole.particles).v[0, 2] < -0.005, "the sphere moves"
    assert_same_state(whole, rest, exact=True, comm=comm)


def bed_file() -> str:
    """Three layers of 8 × 8 touching balls (r = 1 cm) resting on the floor of the box."""
    r = 0.01
    grid = 0.03 + 2 * r * np.arange(8)
    rows = [f"{a} {b} {r + 2 * r * k} {r} 2500" for k in range(3) for a in grid for b in grid]
    return "x y z radius density\n" + "\n".join(rows) + "\n"


@pytest.mark.mpi
def test_restart_continues_a_dense_bed(comm, shared_tmp):
    """A bed of 192 balls whose steps are dense (the contact solver's warm start is carried from step
    to step) under a lid moving down: 2 × 10 steps against 10, checkpoint, 10 give the same
    particles, contact memory and lid."""
    case, mesh, folder = build(comm, shared_tmp, BED, "bed", {"bed.txt": bed_file()})
    whole, rest = continue_from_checkpoint(comm, case, mesh, folder, 10, case.run.dt)
    assert whole.contacts is not None and len(whole.contacts.keys) > 256, "dense steps"
    lid = whole.walls.boundary == list(mesh.boundary_names).index("zmax")
    np.testing.assert_allclose(whole.walls.a[lid, 2], 0.2 - 0.5 * 20 * case.run.dt, rtol=1e-12)
    assert_same_state(whole, rest, exact=True, comm=comm)   # the contact solver runs identically on every rank
