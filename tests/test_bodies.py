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
