"""Output files: the serial cell order that makes fields.h5 independent of the rank count, the
mesh as ParaView reads it, and particles.csv rows."""
import numpy as np
import pytest
from mpi4py import MPI

from pmpm.io import FieldWriter, ParticleWriter, SerialOrder, h5py
from pmpm.mesh import Mesh
from pmpm.particles import ParticleState


@pytest.mark.mpi
def test_serial_order_slabs(comm):
    """Each rank's slab holds the rows of the undistributed order [start, stop), whichever rank
    owns them, and the slabs tile the whole order."""
    mesh = Mesh.from_box(comm, (0, 0, 0), (1, 1, 1), (6, 5, 4))
    owned = mesh.cell_serial[:mesh.n_owned_cells]
    plan = SerialOrder.build(comm, owned, mesh.n_global_cells)
    slab = plan.slab(np.column_stack([owned, 2 * owned]).astype(float))
    np.testing.assert_array_equal(slab[:, 0], np.arange(plan.start, plan.stop))
    np.testing.assert_array_equal(slab[:, 1], 2 * np.arange(plan.start, plan.stop))
    assert comm.allreduce(plan.stop - plan.start) == mesh.n_global_cells


@pytest.mark.mpi
@pytest.mark.parametrize("cell_type", ["hex", "tet"])
def test_fields_h5_mesh_in_vtk_order(comm, shared_tmp, cell_type):
    """/mesh/cells in VTK vertex order: every cell's volume from its vertices (VTK's hexahedron or
    tetrahedron) is positive and equals /mesh/cell_volumes, whose sum is the box's volume; the
    vertex average is /mesh/cell_centers (hexahedra)."""
    folder = shared_tmp / f"fields_{cell_type}_{comm.size}"
    if comm.rank == 0:
        folder.mkdir()
    comm.Barrier()
    mesh = Mesh.from_box(comm, (0, 0, 0), (0.3, 0.2, 0.1), (3, 4, 2), cell_type)
    FieldWriter(comm, folder, mesh, with_fluid=False)
    comm.Barrier()
    with h5py.File(folder / "fields.h5", "r", driver="mpio", comm=comm) as f:
        xyz, cells = f["mesh/vertices"][...], f["mesh/cells"][...]
        volumes, centres = f["mesh/cell_volumes"][...], f["mesh/cell_centers"][...]
    corners = xyz[cells]
    if cell_type == "tet":
        edges = corners[:, 1:] - corners[:, :1]
        from_vertices = np.einsum("ci,ci->c", edges[:, 0], np.cross(edges[:, 1], edges[:, 2])) / 6
    else:   # VTK hexahedron: bottom face 0-1-2-3 counter-clockwise seen from the top face 4-5-6-7
        bottom = np.cross(corners[:, 1] - corners[:, 0], corners[:, 3] - corners[:, 0])
        from_vertices = np.einsum("ci,ci->c", bottom, corners[:, 4] - corners[:, 0])
        np.testing.assert_allclose(corners.mean(axis=1), centres, rtol=1e-12)
    np.testing.assert_allclose(from_vertices, volumes, rtol=1e-12)
    assert volumes.sum() == pytest.approx(0.3 * 0.2 * 0.1, rel=1e-12)


def test_particles_csv_rows_and_columns(tmp_path):
    """One row per particle per output time, by time then id, the columns of the header; a second
    writer refuses to overwrite the file."""
    state = ParticleState.empty().appended(np.array([3, 8]), [[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]], np.ones((2, 3)),
                                           np.zeros((2, 3)), np.array([0.01, 0.02]), np.array([1000.0, 2000.0]),
                                           np.zeros(2, np.int8))
    writer = ParticleWriter(MPI.COMM_SELF, tmp_path, with_fluid=True)
    force = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    writer.write(0.5, state, force, -force)
    writer.write(1.0, state, force, -force)
    table = np.genfromtxt(tmp_path / "particles.csv", delimiter=",", names=True)
    assert table.dtype.names == ParticleWriter.BASE + ParticleWriter.FLUID
    assert table["time"].tolist() == [0.5, 0.5, 1.0, 1.0] and table["id"].tolist() == [3, 8, 3, 8]
    np.testing.assert_array_equal(table["y"], [0.2, 0.5, 0.2, 0.5])
    np.testing.assert_array_equal(table["tz"], [-3.0, -6.0, -3.0, -6.0])
    with pytest.raises(FileExistsError):
        ParticleWriter(MPI.COMM_SELF, tmp_path, with_fluid=False)
