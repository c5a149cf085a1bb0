"""``pmpm render``: pictures from a run's output. A sphere covers the pixels of its true radius,
the nearer of two spheres hides the other, the slice shows the cell values of hexahedra and
tetrahedra in the colours its bar says, pictures are never replaced, and bad input exits 2 with
one line."""
import subprocess

import matplotlib
import numpy as np
import pytest
from matplotlib.image import imread
from mpi4py import MPI

from conftest import PYTHON, subprocess_env
from pmpm.__main__ import main
from pmpm.io import FieldWriter
from pmpm.mesh import Mesh
from pmpm.render import parse_render_arguments, render

BOX = ((0.0, 0.0, 0.0), (0.1, 0.1, 0.1))


def write_output(folder, particles, cell_type="hex", cells=(4, 4, 4), velocity=None, times=(0.0,), solid=None):
    """A run's fields.h5, written in-process by pmpm's own writer: the same particles at each time;
    ``velocity(cell_centres)`` gives the fluid's, or None for a run without a fluid; ``solid(cell
    centres)`` the volume fraction (default 0)."""
    folder.mkdir(exist_ok=True)
    mesh = Mesh.from_box(MPI.COMM_SELF, *BOX, cells, cell_type)
    writer = FieldWriter(MPI.COMM_SELF, folder, mesh, with_fluid=velocity is not None)
    n = len(particles["radius"])
    arrays = {"id": np.arange(n), "position": np.asarray(particles["position"], float).reshape(n, 3),
              "velocity": np.asarray(particles.get("velocity", np.zeros((n, 3))), float).reshape(n, 3),
              "angular_velocity": np.zeros((n, 3)), "radius": np.asarray(particles["radius"], float),
              "density": np.full(n, 1000.0)}
    fields = {}
    if velocity is not None:
        u = velocity(mesh.cell_center)
        fraction = np.zeros(len(u)) if solid is None else solid(mesh.cell_center)
        fields = {"velocity": u, "pressure": u[:, 0].copy(), "volume_fraction": fraction}
    for time in times:
        writer.write(time, fields, arrays)
    return folder


def pmpm_render(*args):
    return render(parse_render_arguments([str(a) for a in args]))


def test_a_sphere_covers_the_pixels_of_its_true_radius(tmp_path):
    """One sphere of radius 2 cm in the middle of a 10 cm box, no fluid: the pixels that are not
    white around its centre number π r² in pixels within 3 %, and the PNG has the size asked."""
    output = write_output(tmp_path / "run", {"position": [[0.05, 0.05, 0.05]], "radius": [0.02]})
    [picture] = pmpm_render(output, "--size", 700, 600)
    image = imread(picture.path)[..., :3]
    assert image.shape[:2] == (600, 700)
    column, row = picture.pixel_of(0.05, 0.05)
    radius = 0.02 / picture.metres_per_pixel
    assert radius > 40
    rows, columns = np.mgrid[:image.shape[0], :image.shape[1]]
    near = np.hypot(columns + 0.5 - column, rows + 0.5 - row) < 1.3 * radius
    covered = near & (image.min(axis=2) < 0.9)
    assert covered.sum() == pytest.approx(np.pi * radius ** 2, rel=0.03)


def test_the_plane_hides_the_part_of_a_sphere_behind_it(tmp_path):
    """A sphere of radius 2 cm whose centre lies 1 cm behind the coloured plane (still fluid, so the
    slice is near-white): only its cap in front shows, a disc of radius √(2² − 1²) = 1.73 cm."""
    output = write_output(tmp_path / "run", {"position": [[0.05, 0.06, 0.05]], "radius": [0.02]},
                          velocity=lambda centre: np.zeros_like(centre))
    [picture] = pmpm_render(output, "--size", 700, 600, "--at", 0.05)
    image = imread(picture.path)[..., :3]
    column, row = picture.pixel_of(0.05, 0.05)
    rows, columns = np.mgrid[:image.shape[0], :image.shape[1]]
    near = np.hypot(columns + 0.5 - column, rows + 0.5 - row) < 0.026 / picture.metres_per_pixel
    visible = np.sqrt(0.02 ** 2 - 0.01 ** 2) / picture.metres_per_pixel
    assert (near & (image.min(axis=2) < 0.9)).sum() == pytest.approx(np.pi * visible ** 2, rel=0.03)


@pytest.mark.parametrize("small_in_front", [True, False])
def test_the_nearer_sphere_hides_the_farther(tmp_path, small_in_front):
    """Two spheres on one line of sight, coloured by radius (small pale, big dark red): the small
    one's centre shows its pale colour only when it is nearer the viewer (looking along +y)."""
    near_y, far_y = 0.03, 0.07
    small_y, big_y = (near_y, far_y) if small_in_front else (far_y, near_y)
    output = write_output(tmp_path / "run", {"position": [[0.05, small_y, 0.05], [0.05, big_y, 0.05]],
                                             "radius": [0.01, 0.02]})
    [picture] = pmpm_render(output, "--size", 500, 400, "--particle-colour", "radius")
    image = imread(picture.path)[..., :3]
    column, row = picture.pixel_of(0.05, 0.05)
    lowest, highest = (matplotlib.colormaps["YlOrRd"](v)[:3] for v in (0.2, 1.0))
    centre = image[int(row), int(column)]
    ring = image[int(row), int(column + 0.015 / picture.metres_per_pixel)]   # on the big sphere only
    assert ring[1] < 0.1                        # dark red: little green
    assert (centre[1] > 0.5) == small_in_front  # the pale small one, if in front
    assert lowest[1] > 0.8 and highest[1] < 0.05


@pytest.mark.parametrize("cell_type", ["hex", "tet"])
def test_the_slice_shows_the_cell_values(tmp_path, cell_type):
    """Fluid at 1 m/s in x < 5 cm and 0.25 m/s beyond (cells of a 4³ box, hexahedra or 6
    tetrahedra each): on the middle plane y = 5 cm, itself a layer of faces, the two halves show
    the colour bar's colours for 1 and 0.25 m/s; the particle's own pixels are drawn over it."""
    def velocity(centre):
        return np.where(centre[:, :1] < 0.05, 1.0, 0.25) * [1.0, 0.0, 0.0]
    output = write_output(tmp_path / "run", {"position": [[0.05, 0.04, 0.08]], "radius": [0.01]},
                          cell_type, velocity=velocity)
    [picture] = pmpm_render(output, "--size", 600, 400, "--vectors")
    image = imread(picture.path)[..., :3]
    blues = matplotlib.colormaps["Blues"]
    for x, speed in ((0.015, 1.0), (0.085, 0.25)):
        column, row = picture.pixel_of(x, 0.035)
        np.testing.assert_allclose(image[int(row), int(column)], blues(speed)[:3], atol=0.02)
    column, row = picture.pixel_of(0.05, 0.08)
    assert np.abs(image[int(row), int(column)] - blues(1.0)[:3]).max() > 0.2


def test_solid_cells_on_the_slice_are_grey(tmp_path):
    """Cells at least half filled (an immersed body in z < 2.5 cm, volume fraction 1; 0.4 above it)
    are drawn grey over the slice's colours: the flow cannot pass there."""
    def solid(centre):
        return np.where(centre[:, 2] < 0.025, 1.0, np.where(centre[:, 2] < 0.05, 0.4, 0.0))
    output = write_output(tmp_path / "run", {"position": [[0.05, 0.05, 0.09]], "radius": [0.005]},
                          velocity=lambda centre: np.ones_like(centre), solid=solid)
    [picture] = pmpm_render(output, "--size", 600, 400)
    image = imread(picture.path)[..., :3]
    column, row = picture.pixel_of(0.05, 0.0125)
    np.testing.assert_allclose(image[int(row), int(column)], 0.6, atol=0.02)
    column, row = picture.pixel_of(0.05, 0.0375)
    assert np.abs(image[int(row), int(column)] - 0.6).max() > 0.1


def test_pictures_are_never_replaced(tmp_path, capsys):
    """Rendering twice numbers the second set of pictures; --times all --every 2 picks times 0
    and 2 of three; one line per picture names it and its time."""
    output = write_output(tmp_path / "run", {"position": [[0.05, 0.05, 0.05]], "radius": [0.01]},
                          times=(0.0, 0.1, 0.2))
    first = pmpm_render(output, "--size", 300, 200, "--times", "all", "--every", 2)
    kept = [p.path.read_bytes() for p in first]
    second = pmpm_render(output, "--size", 300, 200, "--times", "0.1")
    assert [p.path.name for p in first] == ["particles_y_000000.png", "particles_y_000002.png"]
    assert [p.path.name for p in second] == ["particles_y_000001.png"]
    third = pmpm_render(output, "--size", 300, 200, "--times", "0.2")
    assert third[0].path.name == "particles_y_000002.1.png"
    assert [p.path.read_bytes() for p in first] == kept
    assert capsys.readouterr().out.splitlines()[-1].endswith("particles_y_000002.1.png  t = 0.2 s")


@pytest.mark.parametrize("args, message", [
    (["{missing}"], "no such folder"),
    (["{empty}"], "no fields.h5 here"),
    (["{run}", "--field", "temperature"], "argument --field: invalid choice: 'temperature'"),
    (["{run}", "--times", "0.123"], "no output at t = 0.123 s"),
    (["{run}", "--field", "pressure"], "--field pressure: "),
    (["{run}", "--at", "0.5"], "--at 0.5: outside the domain"),
    (["{run}", "--every", "0"], "--every 0: must be a whole number >= 1"),
])
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, args, message):
    run = write_output(tmp_path / "run", {"position": [[0.05, 0.05, 0.05]], "radius": [0.01]})
    (tmp_path / "empty").mkdir()
    paths = {"missing": tmp_path / "missing", "empty": tmp_path / "empty", "run": run}
    status = main(["render"] + [a.format(**paths) for a in args])
    error = capsys.readouterr().err
    assert status == 2 and len(error.splitlines()) == 1 and message in error, error


def test_bad_input_from_the_command_line(tmp_path):
    """The same in a process of its own: exit status 2, one line, no traceback."""
    done = subprocess.run([PYTHON, "-m", "pmpm", "render", str(tmp_path / "missing")], capture_output=True,
                          text=True, timeout=60, env=subprocess_env())
    assert done.returncode == 2 and done.stderr.splitlines() == [f"pmpm: error: render: {tmp_path / 'missing'}: "
                                                                "no such folder"]
