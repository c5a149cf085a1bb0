"""How particles meet the domain's boundaries: walls, inlets (a distributor plate) and symmetry
planes hold them; outlets let them leave, unless ``particles = "wall"``."""
from dataclasses import replace

import numpy as np
import pytest
from mpi4py import MPI

from pmpm.case import load_case
from pmpm.errors import CaseError
from pmpm.simulation import Simulation, build_mesh

FALLING = """
[run]
end_time = 1.0
dt = 0.002
gravity = [0.0, 0.0, -9.81]
[mesh]
box = {{ lower = [0, 0, 0], upper = [0.05, 0.05, 0.1], cells = [5, 5, 10] }}
[fluid]
density = 1.2
viscosity = 1.8e-5
[boundary.zmin]
type = "{bottom}"
{extra}
[boundary.zmax]
type = "outlet"
[collisions]
restitution = 0.5
[[particles.add]]
position = [0.025, 0.025, 0.02]
radius = 0.005
density = 2500.0
"""


def fall(tmp_path, bottom, extra=""):
    """A glass bead dropped 15 mm onto the bottom boundary in air; 0.2 s later: (held, its height)."""
    if bottom == "inlet":
        extra = "velocity = [0.0, 0.0, 0.05]\n" + extra
    path = tmp_path / f"{bottom}.toml"
    path.write_text(FALLING.format(bottom=bottom, extra=extra))
    case = load_case(path, [])
    sim = Simulation(MPI.COMM_SELF, case, build_mesh(MPI.COMM_SELF, case), quiet=True)
    for _ in range(100):
        sim.advance(0.002)
    return len(sim.particles) == 1, (sim.particles.x[0, 2] if len(sim.particles) else None)


def test_particles_meet_inlets_as_walls_and_leave_through_outlets(tmp_path):
    """On an inlet blowing 5 cm/s up (a distributor plate) the bead lands and stays, resting on it
    (its centre one radius up, within 1 %); through an outlet it falls out of the domain, unless the
    outlet says particles = "wall"."""
    held, height = fall(tmp_path, "inlet")
    assert held and height == pytest.approx(0.005, rel=0.01)
    held, _ = fall(tmp_path, "outlet")
    assert not held
    held, height = fall(tmp_path, "outlet", 'particles = "wall"')
    assert held and height == pytest.approx(0.005, rel=0.01)
    held, _ = fall(tmp_path, "inlet", 'particles = "pass"')
    assert not held


def test_a_wall_that_lets_particles_pass_is_refused(tmp_path):
    path = tmp_path / "case.toml"
    path.write_text(FALLING.format(bottom="wall", extra='particles = "pass"'))
    with pytest.raises(CaseError, match='particles = "pass": particles cannot pass a wall'):
        load_case(path, [])


LEAVING = """
[run]
end_time = 1.0
dt = 0.01
gravity = [0.0, 0.0, 0.0]
[mesh]
box = { lower = [0, 0, 0], upper = [0.1, 0.1, 0.1], cells = [4, 4, 4] }
[boundary.zmin]
type = "outlet"
[boundary.xmax]
type = "outlet"
[[particles.add]]              # straight down through zmin, close to the xmin wall
position = [0.01, 0.05, 0.05]
velocity = [0.0, 0.0, -1.0]
radius = 0.002
density = 1000.0
[[particles.add]]              # out through xmax, close to the zmin outlet's edge
position = [0.05, 0.05, 0.01]
velocity = [1.0, 0.0, -0.05]
radius = 0.002
density = 1000.0
[[particles.add]]              # out through the corner region, more along x than down
position = [0.05, 0.02, 0.03]
velocity = [1.0, 0.0, -0.5]
radius = 0.002
density = 1000.0
"""


def test_removed_particles_are_counted_by_the_boundary_they_cross(tmp_path):
    """Three spheres leave a box through two outlets: summary.json's count per boundary names the
    one each crossed (zmin once, xmax twice; nothing through a wall), and a checkpoint keeps it."""
    from pmpm import checkpoint, reporting
    path = tmp_path / "case.toml"
    path.write_text(LEAVING)
    case = load_case(path, [])
    sim = Simulation(MPI.COMM_SELF, case, build_mesh(MPI.COMM_SELF, case), quiet=True)
    for _ in range(12):
        sim.advance(0.01)
    assert len(sim.particles) == 0
    summary = reporting.summary(sim.model, sim.state, "done", {})
    assert summary["particles_removed"] == 3
    assert summary["particles_removed_through"] == {"zmin": 1, "xmax": 2}
    checkpoint.write(MPI.COMM_SELF, tmp_path, sim.mesh, sim.state)
    path = tmp_path / "checkpoint.h5"
    restored = checkpoint.restore(MPI.COMM_SELF, checkpoint.read(MPI.COMM_SELF, path), sim.model, sim.state, path)
    assert restored.removed_through == {"zmin": 1, "xmax": 2}


def test_a_path_counts_through_the_first_boundary_it_crosses_outwards():
    """``BoundaryFaces.crossed`` on a box split into triangles: the boundary crossed first along the
    path (xmax at a third of the path before ymin at two thirds), a path through the diagonal
    edge shared by two triangles of a face (not missed between them), and −1 for a path that stays
    inside, comes in from outside, has no length or is not finite."""
    from pmpm.exits import BoundaryFaces
    from pmpm.mesh import Mesh
    faces = BoundaryFaces.of_mesh(Mesh.from_box(MPI.COMM_SELF, [0, 0, 0], [0.1, 0.1, 0.1], [2, 2, 2]))
    paths = {   # start, end, the boundary crossed first
        "xmax first": ([0.09, 0.02, 0.05], [0.12, -0.01, 0.05], "xmax"),
        "edge": ([0.025, 0.025, 0.01], [0.025, 0.025, -0.01], "zmin"),  # (0.025, 0.025): a quad's diagonal
        "stopped beyond": ([0.02, 0.05, 0.05], [-1e-9, 0.05, 0.05], "xmin"),
        "inside": ([0.02, 0.05, 0.05], [0.08, 0.05, 0.05], None),
        "coming in": ([0.05, 0.05, 0.11], [0.05, 0.05, 0.09], None),
        "still": ([0.05, 0.05, 0.05], [0.05, 0.05, 0.05], None),
        "not finite": ([0.05, 0.05, 0.05], [np.nan, 0.05, 0.05], None),
    }
    start = np.array([p[0] for p in paths.values()])
    end = np.array([p[1] for p in paths.values()])
    crossed = faces.crossed(start, end)
    for (label, (*_, expected)), index in zip(paths.items(), crossed):
        assert (faces.names[index] if index >= 0 else None) == expected, label


@pytest.mark.mpi
def test_particles_that_crossed_the_boundary_are_removed_on_every_rank_count(comm):
    """Stage 8 on 1 rank (``remove_outside``) and on 2 (``migrate_particles``, the boxes cut at
    x = 0.05): a sphere whose path crossed a wall (as one that tunnelled through it would), one that
    stopped just beyond the floor with no speed left (the exit test of ranks before missed it: it
    looked only within 1.5 × |v| dt of an exit) and one through xmax are removed and counted by
    boundary; the one that stayed inside moves to the rank of its new box, its state kept."""
    from pmpm.exits import BoundaryFaces
    from pmpm.mesh import Mesh
    from pmpm.migration import migrate_particles, remove_outside
    from pmpm.ownership import Partition, gather
    from pmpm.particles import ParticleState
    from pmpm.state import RunState
    faces = BoundaryFaces.of_mesh(Mesh.from_box(comm, [0, 0, 0], [0.1, 0.1, 0.1], [2, 2, 2]))
    start = np.array([[0.02, 0.05, 0.05], [0.08, 0.05, 0.005], [0.06, 0.05, 0.05], [0.09, 0.02, 0.05]])
    end = np.array([[-0.001, 0.05, 0.05], [0.08, 0.05, -1e-4], [0.04, 0.05, 0.05], [0.12, -0.01, 0.05]])
    n = len(end)
    moved = ParticleState.empty().appended(np.arange(n), end, np.zeros((n, 3)), np.full((n, 3), 0.5),
                                           np.full(n, 0.004), np.full(n, 2500.0), np.zeros(n, np.int8))
    if comm.size == 1:
        state = RunState(0.0, 0, moved, None, np.zeros((n, 3)), np.zeros((n, 3)), None, n, 0, ())
        after = remove_outside(faces, state, start)
    else:
        lower, upper = np.full((2, 3), -np.inf), np.full((2, 3), np.inf)
        upper[0, 0] = lower[1, 0] = 0.05
        partition = Partition(lower, upper)
        mine = partition.owner_of(start) == comm.rank   # each rank owns what was in its box as the step started
        owned = RunState(0.0, 0, moved.without(~mine), None, np.zeros((mine.sum(), 3)), np.zeros((mine.sum(), 3)),
                         None, n, 0, (), partition=partition)
        after = migrate_particles(comm, faces, owned, start[mine], 1e-3, rebalance=False)
        assert len(after.particles) == (1 if comm.rank == 0 else 0)   # id 2 went to rank 0's box
        after = replace(after, particles=gather(comm, after.particles))
    assert after.removed == 3
    assert after.removed_through == {"xmin": 1, "zmin": 1, "xmax": 1}
    np.testing.assert_array_equal(after.particles.id, [2])
    np.testing.assert_array_equal(after.particles.x, [end[2]])
    np.testing.assert_array_equal(after.particles.omega, [[0.5, 0.5, 0.5]])
