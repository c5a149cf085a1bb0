"""How particles meet the domain's boundaries: walls, inlets (a distributor plate) and symmetry
planes hold them; outlets let them leave, unless ``particles = "wall"``."""
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
