"""Immersed bodies of prescribed motion: their shapes, insides and motion (pmpm.bodies)."""
import numpy as np
import pytest
from mpi4py import MPI

from pmpm.bodies import Body, box_triangles, cylinder_triangles, read_surface, winding_number
from pmpm.coupling.locate import reference_samples
from pmpm.mesh import Mesh


def body(shape, **values) -> Body:
    center = np.array(values.pop("center", (0.1, 0.2, 0.3)))
    base = dict(name="b", shape=shape, center=center, tilt=np.eye(3), size=None, axis=np.array([0.0, 0.0, 1.0]), radius=None,
                length=None, velocity=np.zeros(3), angular_velocity=np.zeros(3), rotation_center=np.zeros(3))
    base.update(values)
    if shape == "box":
        base["triangles"] = box_triangles(center, base["size"])
    else:
        base["triangles"] = cylinder_triangles(center, base["axis"], base["radius"], base["length"])
    return Body(**base)


def test_surfaces_are_closed_and_wound_outwards():
    """The box's and the cylinder's triangles enclose their volumes (divergence theorem, signed:
    outward winding), the box's exactly, the 48-sided cylinder's as a polygon prism."""
    for triangles, volume in ((box_triangles([1.0, 2.0, 3.0], [0.2, 0.3, 0.5]), 0.03),
                              (cylinder_triangles(np.array([0.0, 0.0, 0.0]), [1.0, 1.0, 0.0], 0.1, 0.4),
                               0.4 * 0.5 * 48 * 0.01 * np.sin(2 * np.pi / 48))):
        signed = np.einsum("ij,ij->i", triangles[:, 0], np.cross(triangles[:, 1], triangles[:, 2])).sum() / 6
        assert signed == pytest.approx(volume, rel=1e-12)


def test_inside_of_primitives_and_of_their_surfaces():
    """The primitives' own tests and the winding number of their triangles agree on random points
    (away from the cylinder's facets), and a box read back from an STL file is the same box."""
    rng = np.random.default_rng(4)
    box = body("box", size=np.array([0.2, 0.1, 0.4]))
    points = box.center + rng.uniform(-0.3, 0.3, (2000, 3))
    np.testing.assert_array_equal(box.inside(points, 0.0), winding_number(points, box.triangles) > 0.5)
    tilted = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    cylinder = body("cylinder", axis=tilted, radius=0.1, length=0.3)
    local = points - cylinder.center
    across = np.linalg.norm(local - (local @ tilted)[:, None] * tilted, axis=1)
    clear = np.abs(across - 0.1) > 0.1 * (1 - np.cos(np.pi / 48)) + 1e-9
    np.testing.assert_array_equal(cylinder.inside(points, 0.0)[clear],
                                  (winding_number(points, cylinder.triangles) > 0.5)[clear])
    assert cylinder.inside(points, 0.0).sum() > 50


def test_box_surface_file_round_trip(tmp_path):
    import meshio
    triangles = box_triangles([0.0, 0.0, 0.0], [1.0, 2.0, 3.0])[:, [0, 2, 1]]   # wound inwards on purpose
    meshio.write_points_cells(tmp_path / "box.stl", triangles.reshape(-1, 3),
                              [("triangle", np.arange(36).reshape(12, 3))])
    read = read_surface(tmp_path / "box.stl")
    signed = np.einsum("ij,ij->i", read[:, 0], np.cross(read[:, 1], read[:, 2])).sum() / 6
    assert signed == pytest.approx(6.0, rel=1e-6)


def test_prescribed_motion():
    """A point of the body follows x(t) = c + V t + R(Ω t)(x₀ − c): back and forth exactly, and its
    velocity is the time derivative of that path (central difference, 1e-7)."""
    moving = body("box", size=np.array([0.1, 0.1, 0.1]), velocity=np.array([0.3, 0.0, -0.1]),
                  angular_velocity=np.array([0.0, 2.0, 5.0]), rotation_center=np.array([0.1, 0.0, 0.2]))
    start = np.array([[0.3, 0.1, 0.0], [0.1, 0.2, 0.3]])
    t, h = 0.7, 1e-6
    now = moving.from_start(start, t)
    np.testing.assert_allclose(moving.to_start(now, t), start, atol=1e-15)
    rate = (moving.from_start(start, t + h) - moving.from_start(start, t - h)) / (2 * h)
    np.testing.assert_allclose(moving.velocity_at(now, t), rate, rtol=1e-7)
    assert moving.inside(moving.from_start(moving.center[None], t), t).all()


def test_covered_cells_hold_the_body_volume():
    """A cylinder (r 2 cm, 6 cm long) in a box of 4 mm cells, turned by a rotation: Σ α V over the
    cells it covers is its volume within 1 % (4³ sample points a cell)."""
    mesh = Mesh.from_box(MPI.COMM_SELF, (0, 0, 0), (0.1, 0.1, 0.1), (25, 25, 25))
    cylinder = body("cylinder", center=np.array([0.05, 0.05, 0.05]), axis=np.array([1.0, 0.0, 0.0]), radius=0.02,
                    length=0.06, angular_velocity=np.array([0.0, 0.0, 1.0]),
                    rotation_center=np.array([0.05, 0.05, 0.05]))
    cells, alpha = cylinder.covered_cells(mesh, 0.5, reference_samples("hex", 4))
    covered = np.sum(alpha * mesh.cell_volume[cells])
    assert covered == pytest.approx(np.pi * 0.02 ** 2 * 0.06, rel=0.01)


@pytest.mark.parametrize("shape", ["box", "cylinder"])
def test_covered_cells_sample_only_the_cut_cells_and_agree_with_sampling_all(shape):
    """The cells a moving, tilted box or cylinder covers and its volume fraction in each are the
    same, to the bit, as sampling every cell near it: cells wholly inside or outside are decided by
    the centre's distance to the surface, and only cut cells are sampled."""
    from pmpm.bodies import rotation_matrix
    mesh = Mesh.from_box(MPI.COMM_SELF, (0, 0, 0), (0.1, 0.1, 0.1), (20, 20, 20))
    moving = body(shape, center=np.array([0.05, 0.05, 0.05]), size=np.array([0.06, 0.02, 0.03]), radius=0.02,
                  length=0.05, axis=np.array([1.0, 0.0, 0.0]), tilt=rotation_matrix([0.3, 0.2, 0.1]),
                  angular_velocity=np.array([0.0, 0.0, 2.0]), velocity=np.array([0.01, 0.0, 0.0]),
                  rotation_center=np.array([0.05, 0.05, 0.05]))
    samples = reference_samples("hex", 4)
    cells, alpha = moving.covered_cells(mesh, 0.3, samples)
    corners = mesh.vertex_xyz[mesh.cell_vertices]
    every = moving.inside(np.matmul(samples, corners).reshape(-1, 3), 0.3).reshape(len(corners), -1).mean(axis=1)
    np.testing.assert_array_equal(cells, np.flatnonzero(every > 0))
    np.testing.assert_array_equal(alpha, every[cells])
    assert (alpha == 1).sum() > 10 and ((alpha > 0) & (alpha < 1)).sum() > 10


def test_covered_cells_where_the_surface_cuts_no_cell():
    """A body that holds every cell of the mesh (its surface outside it: no cell is cut) covers each
    wholly; one far away covers none. (With no cut cell on a rank the sampling crashed on that rank
    alone, and the other waited for it: the paddle's 2-rank run hung.)"""
    mesh = Mesh.from_box(MPI.COMM_SELF, (0, 0, 0), (0.1, 0.1, 0.1), (5, 5, 5))
    samples = reference_samples("hex", 4)
    whole = body("box", center=np.array([0.05, 0.05, 0.05]), size=np.array([1.0, 1.0, 1.0]),
                 angular_velocity=np.array([0.0, 0.0, 1.0]), rotation_center=np.array([0.05, 0.05, 0.05]))
    cells, alpha = whole.covered_cells(mesh, 0.1, samples)
    np.testing.assert_array_equal(cells, np.arange(125))
    assert (alpha == 1).all()
    far = body("box", center=np.array([5.0, 5.0, 5.0]), size=np.array([0.1, 0.1, 0.1]))
    assert len(far.covered_cells(mesh, 0.0, samples)[0]) == 0


def test_a_tilted_box_is_turned_about_its_centre():
    """A 0.4 × 0.1 × 0.1 box tilted by 90° about z lies along y: its surface and its inside agree."""
    from pmpm.bodies import rotation_matrix
    tilt = rotation_matrix(np.array([0.0, 0.0, np.pi / 2]))
    center = np.array([0.1, 0.2, 0.3])
    triangles = center + box_triangles(np.zeros(3), [0.4, 0.1, 0.1]) @ tilt.T
    turned = Body("b", "box", center, tilt, np.array([0.4, 0.1, 0.1]), np.array([0.0, 0.0, 1.0]), None, None,
                  np.zeros(3), np.zeros(3), np.zeros(3), triangles)
    assert turned.inside(center + np.array([[0.0, 0.15, 0.0]]), 0.0).all()
    assert not turned.inside(center + np.array([[0.15, 0.0, 0.0]]), 0.0).any()
    extent = np.ptp(triangles.reshape(-1, 3), axis=0)
    np.testing.assert_allclose(extent, [0.1, 0.4, 0.1], atol=1e-15)


PLATE = """
[run]
end_time = 3.0
dt = 0.01
gravity = [0.0, 0.0, 0.0]
[mesh]
box = {{ lower = [0, 0, 0], upper = [0.1, 0.02, 0.04], cells = [10, 2, {cells}] }}
[fluid]
density = 1000.0
viscosity = 1.0
[boundary.xmin]
type = "outlet"
[boundary.xmax]
type = "outlet"
[boundary.ymin]
type = "symmetry"
[boundary.ymax]
type = "symmetry"
[[body]]
shape = "box"
center = [0.05, 0.01, 0.02]
size = [0.2, 0.04, 0.005]
velocity = [0.01, 0.0, 0.0]
"""


def run_case(tmp_path, text, steps, dt, name="case.toml"):
    from pmpm.case import load_case
    from pmpm.simulation import Simulation, build_mesh
    path = tmp_path / name
    path.write_text(text)
    case = load_case(path, [])
    sim = Simulation(MPI.COMM_SELF, case, build_mesh(MPI.COMM_SELF, case), quiet=True)
    for _ in range(steps):
        sim.advance(dt)
    return sim


def test_a_plate_sliding_in_a_channel_has_the_couette_drag(tmp_path):
    """A 5 mm plate sliding at 1 cm/s along the middle of a 4 cm channel of fluid (μ = 1 Pa s,
    open ends, so no pressure gradient): the steady flow in each 17.5 mm gap is Couette's, and the
    drag on the plate 2 μ U A / g. Within 10 % at 7 cells per gap (measured −6.7 %), closer at 14
    (−3.6 %): the penalty's surface lies a fraction of a cell off the plate's."""
    couette = 2 * 1.0 * 0.01 * (0.1 * 0.02) / 0.0175
    ratios = [-run_case(tmp_path, PLATE.format(cells=cells), 300, 0.01, f"plate{cells}.toml").state.body_forces[0, 0]
              / couette for cells in (16, 32)]
    print(f"plate drag / Couette: {ratios[0]:.4f} at 7 cells per gap, {ratios[1]:.4f} at 14")
    assert ratios[0] == pytest.approx(1.0, abs=0.10)
    assert abs(ratios[1] - 1) < abs(ratios[0] - 1)


BLADE = """
[run]
end_time = 3.0
dt = 0.005
gravity = [0.0, 0.0, 0.0]
[mesh]
box = { lower = [-0.05, -0.05, 0], upper = [0.05, 0.05, 0.04], cells = [20, 20, 8] }
[fluid]
density = 1000.0
viscosity = 0.01
[[body]]
shape = "box"
center = [0.0, 0.0, 0.02]
size = [0.07, 0.01, 0.02]
angular_velocity = [0.0, 0.0, 4.0]
rotation_center = [0.0, 0.0, 0.02]
"""


def test_a_rotating_blade_spins_the_fluid_up(tmp_path):
    """A blade (7 × 1 × 2 cm) turning at 4 rad/s in a closed box of liquid: after 0.5 s the liquid
    in the annulus it sweeps turns at over half the blade's own speed there (measured 0.69 Ω r), the
    fluid in the cells it covers wholly moves with it within 1 % of its tip speed (0.3 %), and the
    torque on the blade opposes its rotation."""
    sim = run_case(tmp_path, BLADE, 100, 0.005)
    mesh, u, time = sim.mesh, sim.fluid_state.u, sim.state.time
    blade = sim.model.bodies[0]
    cells, alpha = blade.covered_cells(mesh, time, reference_samples("hex", 4))
    wholly = cells[alpha > 0.99]
    slip = np.linalg.norm(u[wholly] - blade.velocity_at(mesh.cell_center[wholly], time), axis=1)
    r = mesh.cell_center - np.array([0.0, 0.0, 0.02])
    radius = np.hypot(r[:, 0], r[:, 1])
    swept = (radius > 0.01) & (radius < 0.035) & (np.abs(r[:, 2]) < 0.01)
    turning = np.mean((r[swept, 0] * u[swept, 1] - r[swept, 1] * u[swept, 0]) / radius[swept] ** 2 / 4.0)
    print(f"blade: the swept liquid turns at {turning:.2f} Ω r; slip in wholly covered cells ≤ "
          f"{slip.max() / (4 * 0.035):.2%} of the tip speed; torque {sim.state.body_forces[0, 5]:.3e} N m")
    assert len(wholly) > 10
    assert turning > 0.5
    assert slip.max() < 0.01 * 4 * 0.035
    assert sim.state.body_forces[0, 5] < 0


SWEEP = """
[run]
end_time = 1.0
dt = 1e-3
gravity = [0.0, 0.0, -9.81]
[mesh]
box = {{ lower = [-0.1, -0.1, 0.0], upper = [0.1, 0.1, 0.1], cells = [4, 4, 2] }}
[collisions]
restitution = 0.5
friction = 0.3
[[particles.add]]
position = [0.05, 0.03, 0.01]
radius = 0.01
density = 1000.0
[[body]]
shape = "box"
center = [0.0, 0.0, 0.028]
size = [0.14, 0.01, 0.05]
angular_velocity = [0.0, 0.0, {omega}]
rotation_center = [0.0, 0.0, 0.028]
"""


def test_a_rotating_blade_pushes_a_ball_out_of_its_way(tmp_path):
    """A blade turning at 2 rad/s about the vertical, no fluid, sweeps over a ball resting on the
    floor in its path (at 31°, 5.8 cm out): the blade reaches it at t ≈ 0.27 s and then pushes it
    ahead: at t = 0.5 s the ball is ahead of the blade (azimuth) and moves at a good part of the blade's
    speed there, and it never cuts into the blade by more than 1 % of its radius. Without the
    blade's surface the ball would stay where it is."""
    sim = run_case(tmp_path, SWEEP.format(omega=2.0), 0, 1e-3)
    blade = sim.model.bodies[0]
    deepest = 0.0
    for _ in range(500):
        sim.advance(1e-3)
        x = sim.particles.x[0]
        start = blade.to_start(x[None], sim.state.time)[0] - blade.center   # the ball in the blade's frame
        outside = np.maximum(np.abs(start) - 0.5 * blade.size, 0.0)
        deepest = max(deepest, 0.01 - np.linalg.norm(outside))
    x, v = sim.particles.x[0], sim.particles.v[0]
    azimuth, blade_azimuth = np.arctan2(x[1], x[0]), 2.0 * sim.state.time
    speed_of_blade_there = 2.0 * np.hypot(x[0], x[1])
    print(f"ball at {np.degrees(azimuth):.1f}°, blade at {np.degrees(blade_azimuth):.1f}°; ball speed "
          f"{np.linalg.norm(v):.3f} m/s, blade {speed_of_blade_there:.3f} m/s; deepest cut {deepest / 0.01:.2%} of r")
    assert azimuth > blade_azimuth
    assert np.linalg.norm(v) > 0.5 * speed_of_blade_there
    assert deepest < 0.01 * 0.01
    assert np.all(np.abs(x[:2]) < 0.1) and x[2] > 0.0099


def test_a_ball_bounces_on_a_fixed_body_with_its_restitution(tmp_path):
    """A ball dropped from 5 cm onto a fixed table (a box body in the middle of the domain, no
    fluid) leaves it at e = 0.5 of its impact speed, up to the O(g dt) of the time stepping, and
    never sinks into it."""
    table = SWEEP.format(omega=0.0).replace("position = [0.05, 0.03, 0.01]", "position = [0.0, 0.0, 0.12]").replace(
        "upper = [0.1, 0.1, 0.1]", "upper = [0.1, 0.1, 0.2]").replace(
        "size = [0.14, 0.01, 0.05]", "size = [0.1, 0.1, 0.05]").replace("friction = 0.3", "friction = 0.0")
    sim = run_case(tmp_path, table, 0, 1e-3)
    top = 0.028 + 0.025
    impact = np.sqrt(2 * 9.81 * (0.12 - 0.01 - top))
    lowest, rebound = np.inf, 0.0
    for _ in range(150):
        sim.advance(1e-3)
        lowest = min(lowest, sim.particles.x[0, 2] - 0.01)
        rebound = max(rebound, sim.particles.v[0, 2])
    print(f"rebound {rebound / impact:.4f} of the impact speed; lowest {lowest - top:.2e} m over the table")
    assert rebound / impact == pytest.approx(0.5, abs=0.02)
    assert lowest > top - 1e-4


def test_a_body_needs_a_fluid_or_collisions(tmp_path):
    from pmpm.case import load_case
    from pmpm.errors import CaseError
    path = tmp_path / "case.toml"
    path.write_text(SWEEP.format(omega=1.0).replace("[collisions]\nrestitution = 0.5\nfriction = 0.3\n", ""))
    with pytest.raises(CaseError, match=r"\[\[body\]\] acts on nothing without \[fluid\]"):
        load_case(path, [])


@pytest.mark.mpi
def test_the_force_on_a_body_in_one_ranks_cells_is_the_same_on_every_rank():
    """A small box in one corner of the mesh covers cells of one rank only; the fluid's force and
    torque on it, summed over the ranks, are the same floats on every rank (the other rank's empty
    sum was once an array of integers, which the reduction misread into garbage there)."""
    from types import SimpleNamespace
    from pmpm.coupling.bodies import BodyForcing
    comm = MPI.COMM_WORLD
    mesh = Mesh.from_box(comm, [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], (6, 6, 6))
    box = body("box", center=(0.1, 0.1, 0.1), size=np.array([0.15, 0.15, 0.15]))
    forcing = BodyForcing(mesh, [box], SimpleNamespace(penalty_strength=35.0, subcell_points=4), 1000.0, 1e-3)
    u = np.tile([1.0, 0.5, 0.0], (mesh.n_local_cells, 1))
    passes = forcing.begin(0.0, u)
    covering = comm.allgather(len(passes.cell))
    assert sum(covering) > 0 and (comm.size == 1 or min(covering) == 0), covering
    totals = forcing.forces(passes, u, 0.0)
    every = comm.allgather(totals)
    assert totals.dtype == np.float64 and np.isfinite(totals).all() and np.abs(totals[0, :3]).max() > 0
    for other in every:
        np.testing.assert_array_equal(other, totals)
