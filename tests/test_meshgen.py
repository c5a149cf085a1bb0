"""Mesh scripts' building blocks (pmpm.meshgen): blocks with cut-outs and named patches, O-grid
cylinders, read back as pmpm meshes with their boundary names."""
import numpy as np
import pytest
from mpi4py import MPI

from pmpm import meshgen
from pmpm.mesh import Mesh


def test_block_with_a_perforated_plate_and_an_inlet_patch(tmp_path):
    """A 0.2 × 0.1 × 0.1 duct with a 1 cm plate at x = 0.1 holding a 4 cm square hole, and an inlet
    on the lower half of xmin: the volume is the duct's less the plate's, and the patches carry
    their names and areas."""
    x, y, z = np.linspace(0, 0.2, 21), np.linspace(0, 0.1, 11), np.linspace(0, 0.1, 11)

    def plate(centre):
        in_plate = np.abs(centre[:, 0] - 0.105) < 0.005
        in_hole = (np.abs(centre[:, 1] - 0.05) < 0.02) & (np.abs(centre[:, 2] - 0.05) < 0.02)
        return in_plate & ~in_hole

    def patches(centre, normal, default):
        names = np.where(default == "solid", "plate", default)
        return np.where((default == "xmin") & (centre[:, 2] < 0.05), "inlet", names)

    meshgen.write(meshgen.block(x, y, z, solid=plate, name=patches), tmp_path / "duct.msh")
    mesh = Mesh.from_file(MPI.COMM_SELF, tmp_path / "duct.msh")
    assert mesh.cell_volume.sum() == pytest.approx(0.2 * 0.1 * 0.1 - 0.01 * (0.01 - 0.04 ** 2), rel=1e-12)
    areas = mesh.boundary_area()
    assert set(areas) == {"inlet", "xmin", "xmax", "ymin", "ymax", "zmin", "zmax", "plate"}
    assert areas["inlet"] == pytest.approx(0.005, rel=1e-12)
    assert areas["plate"] == pytest.approx(2 * (0.01 - 0.04 ** 2) + 4 * 0.04 * 0.01, rel=1e-12)


def test_cylinder_vessel(tmp_path):
    """An O-grid cylinder of radius 5 cm and height 0.2 m: volume within 3 % of π r² h (its discs
    are mapped squares), walls named as asked."""
    mesh = meshgen.cylinder(0.05, np.linspace(0, 0.2, 11), n_across=10)
    meshgen.write(mesh, tmp_path / "vessel.msh")
    read = Mesh.from_file(MPI.COMM_SELF, tmp_path / "vessel.msh")
    assert read.cell_volume.sum() == pytest.approx(np.pi * 0.05 ** 2 * 0.2, rel=0.03)
    assert set(read.boundary_area()) == {"zmin", "zmax", "wall"}
