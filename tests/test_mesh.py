"""Mesh geometry on 1 and 2 ranks: volumes, closed cells, boundary areas, point location, halos,
for the box (hexahedra, tetrahedra) and for a gmsh file with physical names."""
import meshio
import numpy as np
import pytest
from mpi4py import MPI

from pmpm.errors import CaseError
from pmpm.mesh import Mesh
from pmpm.partition import WORK_TOLERANCE, coordinate_bisection
from pmpm.serial_mesh import VTK_ORDER, box_tetrahedra

LOWER, UPPER, CELLS = np.array([0.0, 0.0, 0.0]), np.array([1.0, 2.0, 3.0]), (4, 3, 5)
SHEAR = 0.3  # the gmsh test mesh is the box sheared by x += SHEAR z: same volume, planar faces


def owned_sum(comm, values):
    return comm.allreduce(float(np.sum(values)))


def closure_error(mesh):
    """Largest |Σ outward area vectors| over the owned cells, relative to a face area."""
    n = mesh.n_local_cells
    interior = mesh.face_cells[:, 1] >= 0
    total = np.stack([np.bincount(mesh.face_cells[:, 0], mesh.face_area_vec[:, d], minlength=n)
                      - np.bincount(mesh.face_cells[interior, 1], mesh.face_area_vec[interior, d], minlength=n)
                      for d in range(3)], axis=1)
    return np.abs(total[:mesh.n_owned_cells]).max() / mesh.face_area.max()


def write_gmsh(path, cell_type):
    """A sheared box as a gmsh 2.2 file with physical surfaces inlet (x=0), outlet (x=1+shear z), walls."""
    if cell_type == "hex":
        nx, ny, nz = CELLS
        axes = [np.linspace(LOWER[d], UPPER[d], n + 1) for d, n in enumerate(CELLS)]
        z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        xyz = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
        i, j, k = [a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")]
        v = lambda a, b, c: (i + a) + (nx + 1) * ((j + b) + (ny + 1) * (k + c))
        volume = np.stack([v(0, 0, 0), v(1, 0, 0), v(1, 1, 0), v(0, 1, 0),
                           v(0, 0, 1), v(1, 0, 1), v(1, 1, 1), v(0, 1, 1)], axis=1)    # VTK order
        block = "hexahedron"
        faces = volume[:, [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]]
        surface_type = "quad"
    else:
        xyz, petsc = box_tetrahedra(LOWER, UPPER, CELLS)
        volume = petsc[:, np.argsort(VTK_ORDER["tet"])]
        block = "tetra"
        faces = volume[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]]
        surface_type = "triangle"
    faces = faces.reshape(-1, faces.shape[-1])
    keys, counts = np.unique(np.sort(faces, axis=1), axis=0, return_counts=True)
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    boundary = faces[first[counts == 1]]
    center = xyz[boundary].mean(axis=1)
    tag = np.full(len(boundary), 3)
    tag[np.isclose(center[:, 0], LOWER[0])] = 1
    tag[np.isclose(center[:, 0], UPPER[0])] = 2
    sheared = xyz.copy()
    sheared[:, 0] += SHEAR * xyz[:, 2]
    mesh = meshio.Mesh(sheared, [(surface_type, boundary), (block, volume)],
                       cell_data={"gmsh:physical": [tag, np.full(len(volume), 10)],
                                  "gmsh:geometrical": [tag, np.full(len(volume), 10)]},
                       field_data={"inlet": np.array([1, 2]), "outlet": np.array([2, 2]),
                                   "walls": np.array([3, 2]), "fluid": np.array([10, 3])})
    meshio.write(str(path), mesh, file_format="gmsh22", binary=False)


@pytest.mark.mpi
@pytest.mark.parametrize("cell_type", ["hex", "tet"])
def test_box_geometry(comm, cell_type):
    mesh = Mesh.from_box(comm, LOWER, UPPER, CELLS, cell_type)
    assert mesh.n_global_cells == np.prod(CELLS) * (1 if cell_type == "hex" else 6)
    assert comm.allreduce(mesh.n_owned_cells) == mesh.n_global_cells
    assert owned_sum(comm, mesh.cell_volume[:mesh.n_owned_cells]) == pytest.approx(6.0, rel=1e-12)
    assert closure_error(mesh) < 1e-12
    areas = mesh.boundary_area()
    expected = {"xmin": 6.0, "xmax": 6.0, "ymin": 3.0, "ymax": 3.0, "zmin": 2.0, "zmax": 2.0}
    assert areas == pytest.approx(expected, rel=1e-12)
    # boundary area vectors point out of the domain
    boundary = mesh.face_boundary >= 0
    outward = np.einsum("ij,ij->i", mesh.face_area_vec[boundary], mesh.face_center[boundary] - (LOWER + UPPER) / 2)
    assert (outward > 0).all()
    # interior area vectors point from owner to neighbour
    interior = ~boundary
    d = mesh.cell_center[mesh.face_cells[interior, 1]] - mesh.cell_center[mesh.face_cells[interior, 0]]
    assert (np.einsum("ij,ij->i", d, mesh.face_area_vec[interior]) > 0).all()
    np.testing.assert_allclose(mesh.lower, LOWER)
    np.testing.assert_allclose(mesh.upper, UPPER)


@pytest.mark.mpi
@pytest.mark.parametrize("cell_type", ["hex", "tet"])
def test_gmsh_file(comm, shared_tmp, cell_type):
    path = shared_tmp / f"sheared_{cell_type}.msh"
    if comm.rank == 0:
        write_gmsh(path, cell_type)
    comm.Barrier()
    mesh = Mesh.from_file(comm, path)
    assert mesh.cell_type == cell_type
    assert owned_sum(comm, mesh.cell_volume[:mesh.n_owned_cells]) == pytest.approx(6.0, rel=1e-12)
    assert closure_error(mesh) < 1e-12
    assert sorted(mesh.boundary_names) == ["inlet", "outlet", "walls"]
    slant = np.hypot(1.0, SHEAR)  # the x faces are tilted by the shear
    walls = 2 * (1.0 * 3.0) + 2 * (1.0 * 2.0)  # y faces (parallelograms, base 1 × height 3) + z faces
    areas = mesh.boundary_area()
    assert areas["inlet"] == pytest.approx(2.0 * 3.0 * slant, rel=1e-12)
    assert areas["outlet"] == pytest.approx(2.0 * 3.0 * slant, rel=1e-12)
    assert areas["walls"] == pytest.approx(walls, rel=1e-12)


@pytest.mark.mpi
def test_point_location_and_ghosts(comm):
    mesh = Mesh.from_box(comm, LOWER, UPPER, CELLS, "hex")
    rng = np.random.default_rng(3)
    points = LOWER + rng.random((200, 3)) * (UPPER - LOWER)
    outside = np.array([[-0.1, 1.0, 1.0], [0.5, 2.5, 1.0]])
    found = mesh.find_owned_cells(np.vstack([points, outside]))
    assert (found[-2:] == -1).all()
    # every inside point is found by exactly one rank (none lies on a face here), in the right cell
    counts = comm.allreduce((found[:-2] >= 0).astype(int))
    assert (counts == 1).all()
    h = (UPPER - LOWER) / CELLS
    mine = found[:-2] >= 0
    expected = (np.floor((points[mine] - LOWER) / h) + 0.5) * h + LOWER
    np.testing.assert_allclose(mesh.cell_center[found[:-2][mine]], expected, atol=1e-12)
    # halo: ghosts receive the owner's value; adding ghosts back counts each copy
    values = np.where(np.arange(mesh.n_local_cells) < mesh.n_owned_cells, mesh.cell_serial, -1).astype(float)
    mesh.update_ghosts(values)
    np.testing.assert_array_equal(values, mesh.cell_serial)
    vectors = np.zeros((mesh.n_local_cells, 3))
    vectors[mesh.n_owned_cells:] = 1.0
    mesh.add_ghosts_to_owners(vectors)
    copies = comm.allreduce(float(vectors[:mesh.n_owned_cells, 0].sum()))
    assert copies == comm.allreduce(mesh.n_local_cells - mesh.n_owned_cells)


@pytest.mark.mpi
def test_boundary_triangles_same_on_every_rank(comm):
    mesh = Mesh.from_box(comm, LOWER, UPPER, CELLS, "hex")
    triangles, boundary, normal = mesh.boundary_triangles(["zmin", "xmax"])
    assert len(triangles) == 2 * (CELLS[0] * CELLS[1] + CELLS[1] * CELLS[2])
    area = 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)
    assert area[boundary == mesh.boundary_names.index("zmin")].sum() == pytest.approx(2.0)
    np.testing.assert_allclose(normal[boundary == mesh.boundary_names.index("xmax")], [[-1, 0, 0]] * 30, atol=1e-14)
    gathered = comm.allgather(triangles)
    for other in gathered:
        np.testing.assert_array_equal(other, triangles)


def test_bad_mesh_files(tmp_path):
    with pytest.raises(CaseError, match="mesh file not found"):
        Mesh.from_file(MPI.COMM_SELF, tmp_path / "missing.msh")
    (tmp_path / "junk.msh").write_text("this is not a mesh\n")
    with pytest.raises(CaseError, match="not a mesh file meshio can read"):
        Mesh.from_file(MPI.COMM_SELF, tmp_path / "junk.msh")
    surface = meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))])
    meshio.write(str(tmp_path / "surface.msh"), surface, file_format="gmsh22", binary=False)
    with pytest.raises(CaseError, match="no hexahedra or tetrahedra"):
        Mesh.from_file(MPI.COMM_SELF, tmp_path / "surface.msh")
    with pytest.raises(CaseError, match="is a folder, not a mesh file"):
        Mesh.from_file(MPI.COMM_SELF, tmp_path)


@pytest.mark.mpi
def test_gmsh_file_whose_only_physical_group_is_a_volume(comm, shared_tmp):
    """gmsh writes only the elements of physical groups: with a volume group alone, the file has no
    surfaces, and every boundary face is the unnamed "boundary" (a fixed wall)."""
    path = shared_tmp / "volume_only.msh"
    if comm.rank == 0:
        write_gmsh(path, "hex")
        full = meshio.read(str(path))
        volume = [i for i, block in enumerate(full.cells) if block.type == "hexahedron"][0]
        only = meshio.Mesh(full.points, [full.cells[volume]],
                           cell_data={k: [v[volume]] for k, v in full.cell_data.items()},
                           field_data={"fluid": np.array([10, 3])})
        meshio.write(str(path), only, file_format="gmsh22", binary=False)
    comm.Barrier()
    mesh = Mesh.from_file(comm, path)
    assert mesh.boundary_names == ["boundary"]
    # the whole surface of the sheared box: the tilted x faces and the walls of test_gmsh_file
    assert mesh.boundary_area()["boundary"] == pytest.approx(2 * 2.0 * 3.0 * np.hypot(1.0, SHEAR) + 10.0, rel=1e-12)


def column_with_a_bed(cells=(9, 3, 22), particles=500, bed_height=7.0):
    """Unit-cell centres of a tall column and random points in its lower third (a settled bed)."""
    axes = [np.arange(n) + 0.5 for n in cells]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    points = np.random.default_rng(0).uniform([0, 0, 0], [cells[0], cells[1], bed_height], (particles, 3))
    return centres, points


def test_bisection_shares_the_particles_work():
    # across the height (the longest extent), one part would hold the whole bed; with the
    # particles' work the cuts go across the width, and every part still has its share of cells
    centres, points = column_with_a_bed()
    cell_of_point = np.ravel_multi_index(np.floor(points).astype(int).T, (9, 3, 22))
    plain = coordinate_bisection(centres, 2)[0]
    assert np.bincount(plain[cell_of_point], minlength=2).tolist() == [500, 0]
    for parts in (2, 4):
        part, boxes = coordinate_bisection(centres, parts, points, np.ones(len(points)))
        cells = np.bincount(part, minlength=parts)
        assert cells.max() - cells.min() <= 1
        shares = np.bincount(part[cell_of_point], minlength=parts) / len(points)
        # each cut within the tolerance of its due share; two levels of cuts compound it
        assert np.abs(shares - 1 / parts).max() <= WORK_TOLERANCE * (1 if parts == 2 else 1.5 / 2)
        # every centre lies in one box, its part's, but where a cut splits a layer of cells with the
        # same coordinate: the plane then runs through that layer
        inside = ((centres[:, None] >= boxes[0][None]) & (centres[:, None] < boxes[1][None])).all(axis=2)
        assert (inside.sum(axis=1) == 1).all()
        elsewhere = np.argmax(inside, axis=1) != part
        planes = np.unique(boxes[np.isfinite(boxes)])
        assert np.isin(centres[elsewhere], planes).any(axis=1).all()


@pytest.mark.mpi
def test_partition_shares_particles_on_ranks(comm):
    # the same column as a distributed mesh: each rank owns half the cells and about half the bed
    centres, points = column_with_a_bed()
    mesh = Mesh.from_box(comm, [0, 0, 0], [9, 3, 22], (9, 3, 22), "hex",
                         work=(points, np.ones(len(points))) if comm.rank == 0 else None)
    assert comm.allreduce(mesh.n_owned_cells, op=MPI.MAX) - comm.allreduce(mesh.n_owned_cells, op=MPI.MIN) <= 1
    mine = np.count_nonzero(mesh.find_owned_cells(points) >= 0) / len(points)
    assert abs(mine - 1 / comm.size) <= WORK_TOLERANCE
