"""Injections (the paper's Table 1): release times, positions, reproducibility from the seed, and
ids that are never reused in a run; the particle file, whose bad values are named by line and column."""
import numpy as np
import pytest
from mpi4py import MPI

from pmpm.case import Section, check_table, load_case
from pmpm.schema import SCHEMA
from pmpm.errors import CaseError
from pmpm.injection import Injector, read_particle_file
from pmpm.simulation import Simulation, build_mesh


def injection(**values) -> Section:
    return Section(check_table({"interval": 0.05, "radius": 0.002, "density": 1000.0, **values},
                               SCHEMA["injection"], "injection", "test"))


def test_releases_are_due_at_start_plus_multiples_of_the_interval():
    """start 0.1, interval 0.05, stop 0.3, 2 per release: by t = 0.2 the releases at 0.1, 0.15 and
    0.2 (6 particles), then those at 0.25 and 0.3, then none; asking twice gives the same answer."""
    injector = Injector(injection(start=0.1, stop=0.3, count=2, position=[0.01, 0.02, 0.03]), 0, seed=1)
    new, next_release = injector.due(0, 0.2)
    assert len(new) == 6 and next_release == 3
    again, _ = injector.due(0, 0.2)
    np.testing.assert_array_equal(again.x, new.x)
    rest, last = injector.due(next_release, 10.0)
    assert len(rest) == 4 and last == 5
    assert len(injector.due(last, 20.0)[0]) == 0
    np.testing.assert_array_equal(new.x, np.tile([0.01, 0.02, 0.03], (6, 1)))


def test_random_injection_is_reproducible_from_the_seed_and_stays_in_its_box():
    """The same seed gives the same positions on any rank and in any run; another seed, or another
    release, other positions; all within [lower, upper]."""
    section = injection(kind="random", count=50, lower=[0.0, 0.1, 0.2], upper=[0.05, 0.2, 0.4])
    first, _ = Injector(section, 0, seed=7).due(0, 0.0)
    same, _ = Injector(section, 0, seed=7).due(0, 0.0)
    other_seed, _ = Injector(section, 0, seed=8).due(0, 0.0)
    second_release = Injector(section, 0, seed=7).release(1)
    np.testing.assert_array_equal(first.x, same.x)
    assert not np.allclose(first.x, other_seed.x) and not np.allclose(first.x, second_release.x)
    assert (first.x >= [0.0, 0.1, 0.2]).all() and (first.x <= [0.05, 0.2, 0.4]).all()
    assert first.x.std(axis=0).min() > 0.01     # spread over the box, not one point


def test_cylindrical_and_rotating_injection_positions():
    """A cylindrical release lies at distance r from its axis and height z along it; a location
    rotating at Ω about a centre has turned by Ω t at the release time t."""
    cylinder = injection(kind="cylindrical", origin=[1.0, 2.0, 3.0], axis=[0.0, 0.0, 2.0], r=0.3, theta=0.7, z=0.4)
    x = Injector(cylinder, 0, seed=1).release(0).x[0]
    assert np.hypot(x[0] - 1.0, x[1] - 2.0) == pytest.approx(0.3, rel=1e-14)
    assert x[2] - 3.0 == pytest.approx(0.4, rel=1e-14)
    turning = injection(start=0.5, position=[0.2, 0.0, 0.0], location_angular_velocity=[0.0, 0.0, np.pi],
                        rotation_center=[0.0, 0.0, 0.0])
    x = Injector(turning, 0, seed=1).release(0).x[0]     # t = 0.5: turned by π/2
    np.testing.assert_allclose(x, [0.0, 0.2, 0.0], atol=1e-15)


def test_particle_file_columns(tmp_path):
    """Columns by name in any order, commas or blanks, velocities left out are zero."""
    path = tmp_path / "p.txt"
    path.write_text("radius, density, z, y, x, vz\n0.01, 1000, 0.3, 0.2, 0.1, -1.0\n0.02 2000 0.6 0.5 0.4 0\n")
    new = read_particle_file(path)
    np.testing.assert_array_equal(new.x, [[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    np.testing.assert_array_equal(new.v, [[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(new.radius, [0.01, 0.02])
    assert not new.omega.any()



def write(tmp_path, text, name="particles.txt"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_columns_comments_and_byte_order_mark(tmp_path):
    path = tmp_path / "particles.txt"
    path.write_bytes("\ufeff# two spheres\nx, y, z, vx, vy, vz, radius, density\n\n0.1 0.2 0.3 1 0 0 0.01 1000\n"
                     "0.4,0.5,0.6,0,0,-1,0.02,2000\n".encode())
    new = read_particle_file(path)
    np.testing.assert_array_equal(new.x, [[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    np.testing.assert_array_equal(new.v, [[1, 0, 0], [0, 0, -1]])
    np.testing.assert_array_equal(new.omega, 0.0)
    assert new.radius.tolist() == [0.01, 0.02] and new.density.tolist() == [1000, 2000]


@pytest.mark.parametrize("row, message", [
    ("0.1 0.2 nan 0 0 0 0.01 1000", "line 5: z = nan: must be finite (m)"),
    ("nan 0.2 0.3 0 0 0 0.01 1000", "line 5: x = nan: must be finite (m)"),
    ("0.1 0.2 0.3 0 inf 0 0.01 1000", "line 5: vy = inf: must be finite (m/s)"),
    ("0.1 0.2 0.3 0 0 0 -0.01 1000", "line 5: radius = -0.01: must be finite and > 0 (m)"),
    ("0.1 0.2 0.3 0 0 0 0.01 0", "line 5: density = 0: must be finite and > 0 (kg/m³)"),
    ("0.1 0.2 0.3 0 0 0 0.01", "line 5: 7 values for 8 columns"),
])
def test_bad_value_is_named_by_its_line_and_column(tmp_path, row, message):
    # a comment and a blank line before it: the line number is the file's
    path = write(tmp_path, f"x y z vx vy vz radius density\n# note\n0.1 0.2 0.3 0 0 0 0.01 1000\n\n{row}\n")
    with pytest.raises(CaseError) as error:
        read_particle_file(path)
    assert str(error.value) == f"{path}: {message}"


def test_folder_and_unreadable_file(tmp_path):
    with pytest.raises(CaseError, match="is a folder, not a particle file"):
        read_particle_file(tmp_path)
    with pytest.raises(CaseError, match="particle file not found"):
        read_particle_file(tmp_path / "missing.txt")
    (tmp_path / "binary.txt").write_bytes(b"x y z radius density\n\xff\xfe\x00\x01\n")
    with pytest.raises(CaseError, match="cannot read the particle file"):
        read_particle_file(tmp_path / "binary.txt")


FALLING_THROUGH = """
[run]
end_time = 0.2
dt = 0.01
gravity = [0.0, 0.0, 0.0]
[mesh]
box = { lower = [0, 0, 0], upper = [0.1, 0.1, 0.1], cells = [4, 4, 4] }
[boundary.zmin]
type = "outlet"
[[injection]]
position = [0.05, 0.05, 0.09]
velocity = [0.0, 0.0, -0.5]
interval = 0.01
radius = 0.002
density = 1000.0
[[injection]]
position = [0.02, 0.02, 0.015]
velocity = [0.0, 0.0, -2.0]
start = 0.03
interval = 0.04
radius = 0.002
density = 1000.0
"""


def test_ids_are_never_reused(tmp_path):
    """Particles leave through an outlet while others are injected: an id that has left never
    comes back on a new particle (the fast, later-injected ones leave first, holding the largest
    ids), and every particle ever injected is counted once: held + removed = ids given."""
    path = tmp_path / "case.toml"
    path.write_text(FALLING_THROUGH)
    case = load_case(path, [])
    sim = Simulation(MPI.COMM_SELF, case, build_mesh(MPI.COMM_SELF, case), quiet=True)
    gone, held = set(), set()
    for _ in range(20):
        sim.advance(0.01)
        now = set(sim.particles.id.tolist())
        assert not (now & gone), "an id that left came back"
        gone |= held - now
        held = now
    assert sim.state.removed > 3 and gone
    assert len(sim.particles) + sim.state.removed == sim.state.next_id


def test_cylindrical_angle_is_measured_from_the_documented_reference():
    """θ from +x towards +y about axis z, from +y towards +z about axis x, from +z towards +x
    about axis y (the cyclic order; docs/case_keys.md)."""
    for axis, zero, quarter in (([0, 0, 1], [1, 0, 0], [0, 1, 0]), ([1, 0, 0], [0, 1, 0], [0, 0, 1]),
                                ([0, 1, 0], [0, 0, 1], [1, 0, 0])):
        for theta, direction in ((0.0, zero), (np.pi / 2, quarter)):
            section = injection(kind="cylindrical", origin=[0.0, 0.0, 0.0], axis=axis, r=0.5, theta=theta)
            np.testing.assert_allclose(Injector(section, 0, seed=1).release(0).x[0], 0.5 * np.array(direction),
                                       atol=1e-15)


def test_a_rotating_location_turns_the_release_velocity_and_adds_its_own_motion():
    """A location rotating about z at Ω = π rad/s, released at t = 0.5 s (turned by 90°): the
    point (0.2, 0, 0) is at (0, 0.2, 0), the velocity (0.2, 0, 0) has turned to (0, 0.2, 0) and
    gained the location's own Ω × r = (−0.2 π, 0, 0), and the particle spins with it at Ω."""
    section = injection(start=0.5, position=[0.2, 0.0, 0.0], velocity=[0.2, 0.0, 0.0],
                        location_angular_velocity=[0.0, 0.0, np.pi])
    released = Injector(section, 0, seed=1).release(0)
    np.testing.assert_allclose(released.x[0], [0.0, 0.2, 0.0], atol=1e-15)
    np.testing.assert_allclose(released.v[0], [-0.2 * np.pi, 0.2, 0.0], atol=1e-15)
    np.testing.assert_allclose(released.omega[0], [0.0, 0.0, np.pi], atol=1e-15)


RELEASE_BETWEEN_STEPS = """
[run]
end_time = 0.05
dt = 0.01
gravity = [0.0, 0.0, 0.0]
[mesh]
box = { lower = [0, 0, 0], upper = [0.1, 0.1, 0.1], cells = [4, 4, 4] }
[[injection]]
position = [0.02, 0.05, 0.05]
velocity = [1.0, 0.0, 0.0]
start = 0.013
stop = 0.013
interval = 1.0
radius = 0.002
density = 1000.0
"""


def simulate(tmp_path, text, comm=MPI.COMM_SELF, name="case.toml"):
    # ranks that each run on MPI.COMM_SELF in a shared folder write files of their own
    path = tmp_path / (name if comm.size == MPI.COMM_WORLD.size else f"rank{MPI.COMM_WORLD.rank}_{name}")
    if comm.rank == 0:
        path.write_text(text)
    comm.Barrier()
    case = load_case(path, [])
    return Simulation(comm, case, build_mesh(comm, case), quiet=True)


def test_a_release_between_two_steps_happens_at_its_own_time(tmp_path):
    """Released at t = 0.013 s at 1 m/s with steps of 0.01 s: at t = 0.02 s the particle is 7 mm
    from its release point, not a whole step's 10 mm (it used to be released at the start of the
    step that holds its release time)."""
    sim = simulate(tmp_path, RELEASE_BETWEEN_STEPS)
    sim.advance(0.01)
    assert len(sim.particles) == 0
    sim.advance(0.01)
    assert sim.particles.x[0, 0] - 0.02 == pytest.approx(0.007, abs=1e-12)


CROWDED = """
[run]
end_time = 0.1
dt = 0.001
gravity = [0.0, 0.0, 0.0]
[mesh]
box = { lower = [0, 0, 0], upper = [0.1, 0.1, 0.1], cells = [4, 4, 4] }
[collisions]
[[injection]]
kind = "random"
lower = [0.0, 0.0, 0.0]
upper = [0.1, 0.1, 0.03]
count = 60
interval = 1.0
radius = 0.006
density = 1000.0
"""


@pytest.mark.mpi
def test_random_releases_keep_clear_of_walls_and_each_other(comm, shared_tmp):
    """60 spheres (r = 6 mm) released at random in a slab reaching the walls: every one placed lies
    clear of the walls and of the others; those whose first position would not do were placed at a
    later one or dropped, and the counts add up; the same spheres on 1 and 2 ranks."""
    placed = []
    for c in (comm, MPI.COMM_SELF):
        sim = simulate(shared_tmp, CROWDED, c, name=f"crowded_{comm.size}.toml")
        sim.advance(0.001)
        x, counts = sim.particles.x, sim.state.injection_counts
        assert counts["placed"] + counts["retried"] + counts["dropped"] == 60
        assert counts["retried"] > 5 and len(x) == counts["placed"] + counts["retried"]
        assert (x - 0.006 >= -1e-12).all() and (x + 0.006 <= 0.1 + 1e-12).all()
        gaps = np.linalg.norm(x[:, None] - x[None], axis=2) + np.eye(len(x))
        assert gaps.min() >= 0.012 * (1 - 1e-9)
        placed.append(x)
    np.testing.assert_array_equal(*placed)
