"""Pictures of a run's output: ``pmpm render OUTPUT_DIR`` writes one PNG per output time asked.

Reads ``fields.h5`` (README, "Outputs") and draws, in an orthographic view along the axis normal
to the chosen plane:

- the particles as spheres of their true radius: each one rasterised per pixel with its own depth,
  so overlapping spheres hide each other correctly, and shaded (diffuse light from the upper left
  and a highlight) so that a disc reads as a sphere; coloured by speed or radius;
- the flow on that plane: the polygons where the plane cuts the cells (exact for hexahedra and
  tetrahedra: they tile the plane without gaps or overlaps), coloured by the cell value the solver
  stores, optionally with subsampled velocity vectors. The slice is opaque: a sphere, or the part
  of one, behind it is hidden, as in ParaView;
- the domain's outline: the boundary's feature edges (sharp corners) and silhouette edges.

One process, no MPI or PETSc; matplotlib's Agg backend, no display. Bad input raises
:class:`pmpm.errors.CaseError` (exit status 2).
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import CaseError
from .render_geometry import VIEWS, View, arrow_points, domain_outline, shade_spheres, slice_polygons

FIELDS = {"speed": ("fluid speed", "m/s", "Blues"),
          "pressure": ("pressure less ρ g·x", "Pa", "PRGn"),     # as written: hydrostatic part removed
          "volume_fraction": ("particle volume fraction", "–", "Greys")}
PARTICLE_COLOURS = {"speed": ("particle speed", "m/s"), "radius": ("particle radius", "m")}
PARTICLE_COLOURMAP = "YlOrRd"
ARROWS_ACROSS = 24  # velocity vectors along the longer side of the slice
SUPERSAMPLING = 2   # particle pixels per picture pixel, per direction: smooth rims between spheres

USAGE = """pmpm render OUTPUT_DIR [--plane x|y|z] [--at VALUE] [--times all|last|T1,T2...] [--every N]
                   [--size W H] [--out DIR] [--field speed|pressure|volume_fraction|none]
                   [--vectors] [--particle-colour speed|radius]

Writes one PNG per output time asked (default: the last) into OUTPUT_DIR/pictures/. Examples:
  pmpm render cases/settling_sphere/output --vectors
  pmpm render output --plane z --times all --every 5 --size 800 600"""


class _Parser(argparse.ArgumentParser):
    """argparse that raises CaseError (exit status 2, one line) instead of printing usage."""

    def error(self, message):
        raise CaseError(f"render: {message} (see pmpm render --help)")


def parse_render_arguments(argv: list[str]) -> argparse.Namespace:
    """The render command's options (see ``USAGE``)."""
    parser = _Parser(prog="pmpm render", usage=USAGE)
    parser.add_argument("output_dir", type=Path, help="a run's output folder (holding fields.h5)")
    parser.add_argument("--plane", choices=tuple(VIEWS), default="y",
                        help="normal of the slice plane, also the viewing direction (default y: x right, z up)")
    parser.add_argument("--at", type=float, metavar="VALUE",
                        help="the plane's coordinate along its normal in metres (default: the domain's middle)")
    parser.add_argument("--times", default="last", metavar="all|last|T1,T2...",
                        help="output times to draw (default: last)")
    parser.add_argument("--every", type=int, default=1, metavar="N", help="every N-th of the times asked")
    parser.add_argument("--size", type=int, nargs=2, metavar=("W", "H"),
                        help="picture size in pixels (default: 900 high, as wide as the domain needs)")
    parser.add_argument("--out", type=Path, metavar="DIR", help="folder for the PNGs (default OUTPUT_DIR/pictures)")
    parser.add_argument("--field", choices=(*FIELDS, "none"),
                        help="cell field coloured on the plane (default speed with a fluid)")
    parser.add_argument("--vectors", action="store_true", help="velocity vectors on the plane")
    parser.add_argument("--particle-colour", choices=tuple(PARTICLE_COLOURS), default="speed",
                        help="what the particles' colour shows (default speed)")
    arguments = parser.parse_args(argv)
    if arguments.every < 1:
        raise CaseError(f"render: --every {arguments.every}: must be a whole number >= 1")
    if arguments.size is not None and not (200 <= arguments.size[0] <= 10000 and 150 <= arguments.size[1] <= 10000):
        raise CaseError(f"render: --size {' '.join(map(str, arguments.size))}: must be 200..10000 by 150..10000 pixels")
    return arguments


@dataclass
class RunOutput:
    """What a picture needs from ``fields.h5``: the mesh and the list of output times.

    Attributes
    ----------
    path : Path
        The fields.h5 file.
    vertices : ndarray, shape (n_vertices, 3)
        Mesh vertex coordinates (m).
    cells : ndarray, shape (n_cells, 8 or 4)
        Vertex indices of each hexahedron or tetrahedron, VTK order.
    groups : list of str
        HDF5 group of each output time, in time order.
    times : ndarray, shape (n_times,)
        Output times (s).
    cell_fields : tuple of str
        Cell fields written (empty without a fluid).
    name : str
        The case's name, for titles.
    """

    path: Path
    vertices: np.ndarray
    cells: np.ndarray
    groups: list
    times: np.ndarray
    cell_fields: tuple
    name: str

    @classmethod
    def read(cls, folder: Path) -> "RunOutput":
        if not folder.is_dir():
            raise CaseError(f"render: {folder}: no such folder")
        path = folder / "fields.h5"
        if not path.is_file():
            raise CaseError(f"render: {folder}: no fields.h5 here (is it a pmpm output folder?)")
        import h5py
        try:
            with h5py.File(path, "r") as f:
                vertices, cells = f["mesh/vertices"][...], f["mesh/cells"][...]
                groups = sorted(f["output"])
                times = np.array([f["output"][g].attrs["time"] for g in groups], float)
                cell_fields = tuple(name for name in ("velocity", "pressure", "volume_fraction")
                                    if groups and name in f["output"][groups[0]])
        except (OSError, KeyError) as error:
            raise CaseError(f"render: {path}: not a pmpm fields file ({error})") from None
        if not groups:
            raise CaseError(f"render: {path}: holds no output time yet")
        if len(vertices) < 2 ** 31:   # half the memory for the face and edge sorts of big meshes
            cells = cells.astype(np.int32)
        return cls(path, vertices, cells, [f"output/{g}" for g in groups], times, cell_fields, case_name(folder))

    def select(self, times_asked: str, every: int) -> np.ndarray:
        """Indices of the output times asked: ``all``, ``last`` or times in seconds, comma-separated."""
        if times_asked == "all":
            chosen = np.arange(len(self.times))
        elif times_asked == "last":
            chosen = np.array([len(self.times) - 1])
        else:
            try:
                wanted = [float(text) for text in times_asked.split(",")]
            except ValueError:
                raise CaseError(f"render: --times {times_asked}: must be all, last or times in seconds "
                                "separated by commas") from None
            chosen = []
            for time in wanted:
                nearest = int(np.argmin(np.abs(self.times - time)))
                if abs(self.times[nearest] - time) > 1e-6 * max(abs(time), 1e-3):
                    raise CaseError(f"render: --times: no output at t = {time:g} s in {self.path} "
                                    f"(it holds {describe_times(self.times)})")
                chosen.append(nearest)
            chosen = np.array(chosen)
        return chosen[::every]


def case_name(folder: Path) -> str:
    """The case's folder name from summary.json, else the output folder's name."""
    try:
        case_file = Path(json.loads((folder / "summary.json").read_text())["case"])
        return case_file.parent.name if case_file.name == "case.toml" else case_file.stem
    except (OSError, ValueError, KeyError, TypeError):
        return folder.resolve().name


def describe_times(times: np.ndarray) -> str:
    """A short list of times for an error message: all of them, or the first and last few."""
    shown = [f"{t:g}" for t in times]
    if len(shown) > 8:
        shown = shown[:4] + ["..."] + shown[-2:]
    return f"{len(times)} times: {', '.join(shown)} s"


@dataclass
class Frame:
    """One output time's data for a picture.

    Attributes
    ----------
    time : float
        Simulated time (s).
    position, velocity : ndarray, shape (n_particles, 3)
        Particle centres (m) and velocities (m/s).
    radius : ndarray, shape (n_particles,)
        Particle radii (m).
    slice_values : ndarray, shape (n_slice_cells,) or None
        The coloured field in the cells the plane cuts.
    slice_velocity : ndarray, shape (n_slice_cells, 3) or None
        Fluid velocity in those cells (m/s), for vectors.
    slice_solid : ndarray, shape (n_slice_cells,) of bool, or None
        The cells on the slice at least half filled by particles or immersed bodies.
    """

    time: float
    position: np.ndarray
    velocity: np.ndarray
    radius: np.ndarray
    slice_values: np.ndarray | None
    slice_velocity: np.ndarray | None
    slice_solid: np.ndarray | None = None


def read_frame(run: RunOutput, index: int, slice_cells: np.ndarray, field: str | None, vectors: bool) -> Frame:
    """Read output time ``index``: particles, and the cell field on the slice cells only."""
    import h5py
    with h5py.File(run.path, "r") as f:
        group = f[run.groups[index]]
        try:
            particles = group["particles"]
            position = particles["position"][...].reshape(-1, 3)
            velocity = particles["velocity"][...].reshape(-1, 3)
            radius = particles["radius"][...].reshape(-1)
            slice_velocity = group["velocity"][...][slice_cells] if (vectors or field == "speed") else None
            values = group[field][...][slice_cells] if field not in (None, "speed") else None
            solid = (group["volume_fraction"][...][slice_cells] >= 0.5
                     if len(slice_cells) and "volume_fraction" in run.cell_fields else None)
        except KeyError as error:   # a run killed while writing this time
            raise CaseError(f"render: {run.path}: /{run.groups[index]} is incomplete ({error})") from None
    if field == "speed":
        values = np.linalg.norm(slice_velocity, axis=1)
    return Frame(float(run.times[index]), position, velocity, radius, values, slice_velocity, solid)


def colour_limits(values: list[np.ndarray], robust: bool, from_zero: bool = True) -> tuple[float, float]:
    """Colour range over all the pictures of one command, so that a series of frames compares.

    ``robust`` takes the 1st and 99th percentiles (a pressure spike at one cell would wash out the
    rest); otherwise the minimum (or 0, ``from_zero``, if lower) to the maximum.
    """
    joined = np.concatenate([v for v in values if v is not None and v.size] or [np.zeros(1)])
    if robust:
        low, high = np.percentile(joined, [1, 99])
    else:
        low, high = (min(joined.min(), 0.0) if from_zero else joined.min()), joined.max()
    if high <= low:
        high = low + (abs(low) * 1e-3 if low else 1e-3)
    return float(low), float(high)


def new_picture_path(folder: Path, stem: str) -> Path:
    """``folder/stem.png``, or ``stem.1.png``, ``stem.2.png``... if taken: a picture is never replaced."""
    path, n = folder / f"{stem}.png", 0
    while path.exists():
        n += 1
        path = folder / f"{stem}.{n}.png"
    return path


@dataclass
class Picture:
    """A picture written, and where its axes lie in it (pixel positions of points, for tests).

    Attributes
    ----------
    path : Path
    time : float
        Simulated time shown (s).
    size : (int, int)
        Width and height (pixels).
    limits : (float, float, float, float)
        Axes limits: left, right, bottom, top (m).
    axes_origin : (float, float)
        Pixel position of the axes' lower-left corner, from the picture's lower-left corner.
    metres_per_pixel : float
    """

    path: Path
    time: float
    size: tuple
    limits: tuple
    axes_origin: tuple
    metres_per_pixel: float

    def pixel_of(self, right: float, up: float) -> tuple[float, float]:
        """(column, row) in the PNG, row 0 at the top, of a point in picture coordinates (m)."""
        height = self.size[1]
        column = self.axes_origin[0] + (right - self.limits[0]) / self.metres_per_pixel
        return column, height - (self.axes_origin[1] + (up - self.limits[2]) / self.metres_per_pixel)


def render_frame(frame: Frame, run: RunOutput, view: View, plane_at: float, polygons: np.ndarray | None,
                 outline: np.ndarray, options: argparse.Namespace, field_limits, particle_limits,
                 path: Path) -> Picture:
    """Draw one picture and write it as a new PNG at ``path`` (never replacing a file)."""
    # A Figure of its own, not pyplot's: no display, no global state, nothing to close.
    import matplotlib
    from matplotlib import cm, colors
    from matplotlib.collections import LineCollection, PolyCollection
    from matplotlib.figure import Figure

    width, height = options.size
    field = options.field
    figure = Figure(figsize=(width / 100, height / 100), dpi=100, layout="compressed")
    axes = figure.add_subplot()
    limits = picture_limits(outline)
    axes.set_xlim(limits[0], limits[1])
    axes.set_ylim(limits[2], limits[3])
    axes.set_aspect("equal", adjustable="box")
    axes.set_autoscale_on(False)
    axes.set_xlabel(f"{view.right_name} (m)")
    axes.set_ylabel(f"{view.up_name} (m)")
    n_particles = len(frame.radius)
    drawn = "1 particle at its true radius" if n_particles == 1 else f"{n_particles} particles at their true radius"
    if field is not None:   # the opaque slice hides what lies wholly behind it
        behind = np.count_nonzero(view.nearness(frame.position) + frame.radius <= view.nearness_of(plane_at))
        drawn += f" ({behind} behind the plane)" if behind else ""
    title = f"{run.name} — t = {frame.time:.4g} s\n{drawn}, view along {view.looking}"
    if options.vectors:
        title += "\n" + draw_vectors(axes, polygons, frame.slice_velocity, view)
    if frame.slice_solid is not None and frame.slice_solid.any():
        title += "\ngrey: cells at least half solid"
    axes.set_title(title, fontsize="medium")

    if field is not None:
        label, unit, colourmap = FIELDS[field]
        field_norm = colors.Normalize(*field_limits)
        slice_collection = PolyCollection(polygons, array=frame.slice_values, cmap=colourmap, norm=field_norm,
                                          edgecolors="face", linewidths=0.3, zorder=1)
        axes.add_collection(slice_collection)
        figure.colorbar(slice_collection, ax=axes, shrink=0.8, pad=0.01,
                        extend="both" if field == "pressure" else "neither",
                        label=f"{label} on {view.normal_name} = {plane_at:.4g} m ({unit})")
    if frame.slice_solid is not None and frame.slice_solid.any():   # what the flow cannot pass: a body, a particle
        axes.add_collection(PolyCollection(polygons[frame.slice_solid], facecolors="0.6", edgecolors="face",
                                           linewidths=0.3, zorder=1.5))
    axes.add_collection(LineCollection(outline, colors="0.25", linewidths=1.0, zorder=2))

    particle_label, particle_unit = PARTICLE_COLOURS[options.particle_colour]
    particle_norm = colors.Normalize(*particle_limits)
    particle_colourmap = colors.LinearSegmentedColormap.from_list(
        "particles", matplotlib.colormaps[PARTICLE_COLOURMAP](np.linspace(0.2, 1.0, 256)))
    if n_particles:
        figure.colorbar(cm.ScalarMappable(particle_norm, particle_colourmap), ax=axes, shrink=0.8, pad=0.01,
                        label=f"{particle_label} ({particle_unit})")

    # Fix the layout now: the particle image must match the axes' pixels one to one.
    figure.draw_without_rendering()
    figure.set_layout_engine("none")
    box = axes.get_window_extent()
    n_x, n_y = max(int(round(box.width)), 1), max(int(round(box.height)), 1)
    metres_per_pixel = (limits[1] - limits[0]) / n_x
    if n_particles:
        values = frame.radius if options.particle_colour == "radius" else np.linalg.norm(frame.velocity, axis=1)
        plane = view.nearness_of(plane_at) if (field is not None or options.vectors) else None
        draw_spheres(axes, frame, view, particle_colourmap(particle_norm(values))[:, :3], plane,
                     (limits[0], limits[2]), metres_per_pixel, (n_y, n_x))
    with open(path, "xb") as file:    # exclusive: never replaces a picture
        figure.savefig(file, format="png", dpi=100)
    return Picture(path, frame.time, (width, height), limits, (box.x0, box.y0), metres_per_pixel)


def draw_spheres(axes, frame: Frame, view: View, colour: np.ndarray, plane: float | None,
                 corner: tuple[float, float], metres_per_pixel: float, shape: tuple[int, int]) -> None:
    """The particles as shaded spheres, rasterised at ``SUPERSAMPLING`` × the picture's pixels and
    averaged down, as images filling the axes: the part behind ``plane`` (nearness, m) under the
    slice, the rest over everything.

    Parameters
    ----------
    colour : ndarray, shape (n_particles, 3)
        Base RGB colour of each sphere.
    corner : (float, float)
        Picture coordinates (m) of the axes' lower-left corner.
    shape : (int, int)
        Rows and columns of the axes in picture pixels.
    """
    to_pixels = SUPERSAMPLING / metres_per_pixel
    layers = shade_spheres((view.project(frame.position) - corner) * to_pixels,
                           view.nearness(frame.position) * to_pixels, frame.radius * to_pixels, colour,
                           (shape[0] * SUPERSAMPLING, shape[1] * SUPERSAMPLING),
                           None if plane is None else plane * to_pixels)
    extent = (corner[0], corner[0] + shape[1] * metres_per_pixel, corner[1], corner[1] + shape[0] * metres_per_pixel)
    for layer, zorder in zip(layers, (0.5, 3)):   # under the slice (zorder 1), over everything
        if layer is not None:
            axes.imshow(downsample(layer, SUPERSAMPLING), origin="lower", extent=extent,
                        interpolation="nearest", zorder=zorder)


def draw_vectors(axes, polygons: np.ndarray, velocity: np.ndarray, view: View) -> str:
    """Velocity vectors on the plane, on a regular grid (``ARROWS_ACROSS`` along the slice's longer
    side, or one per cell on coarser meshes), each the velocity of the cell under it, scaled so that
    the largest is one grid spacing long. Returns the line that says so, for the title."""
    corners = polygons.reshape(-1, 2)
    spacing = (corners.max(axis=0) - corners.min(axis=0)).max() / ARROWS_ACROSS
    extent = polygons.max(axis=1) - polygons.min(axis=1)
    spacing = max(spacing, float(np.median(extent.max(axis=1))), 1e-300)
    points, cell = arrow_points(polygons, spacing)
    in_plane = velocity[cell][:, [view.right, view.up]]
    reference = float(np.linalg.norm(in_plane, axis=1).max()) if len(cell) else 0.0
    if reference == 0.0:
        return "arrows: in-plane fluid velocity, zero everywhere"
    axes.quiver(points[:, 0], points[:, 1], in_plane[:, 0], in_plane[:, 1], angles="xy", scale_units="xy",
                scale=reference / spacing, pivot="middle", width=0.003, minlength=0, color="black", edgecolor="white",
                linewidth=0.3, zorder=2.5)
    return f"arrows: in-plane fluid velocity, the longest {reference:.3g} m/s"


def picture_limits(outline: np.ndarray) -> tuple[float, float, float, float]:
    """Axes limits (left, right, bottom, top) in metres: the outline's box and a 3 % margin."""
    lower, upper = outline.reshape(-1, 2).min(axis=0), outline.reshape(-1, 2).max(axis=0)
    margin = 0.03 * (upper - lower).max()
    return (lower[0] - margin, upper[0] + margin, lower[1] - margin, upper[1] + margin)


def default_size(limits, n_colourbars: int) -> tuple[int, int]:
    """Picture size (pixels) that fits the domain's shape: 900 high with room for the title,
    labels and colour bars, at most 1600 wide (then less high)."""
    aspect = (limits[1] - limits[0]) / (limits[3] - limits[2])
    beside, above = 110 + 110 * n_colourbars, 130    # pixels for labels, colour bars, title
    width = aspect * (900 - above) + beside
    if width <= 1600:
        return int(max(width, 500)), 900
    return 1600, int(max((1600 - beside) / aspect + above, 300))


def downsample(layer: np.ndarray, factor: int) -> np.ndarray:
    """Average ``factor`` × ``factor`` blocks of a straight-alpha RGBA image (alpha-weighted colour)."""
    n_y, n_x = layer.shape[0] // factor, layer.shape[1] // factor
    blocks = layer[:n_y * factor, :n_x * factor].reshape(n_y, factor, n_x, factor, 4)
    alpha = blocks[..., 3].mean(axis=(1, 3))
    colour = (blocks[..., :3] * blocks[..., 3:]).mean(axis=(1, 3)) / np.maximum(alpha, 1e-12)[..., None]
    return np.concatenate([np.clip(colour, 0, 1), alpha[..., None]], axis=-1)


def render(arguments: argparse.Namespace) -> list[Picture]:
    """Write the pictures asked for; print one line per picture."""
    run = RunOutput.read(arguments.output_dir)
    with_fluid = "velocity" in run.cell_fields
    field = arguments.field or ("speed" if with_fluid else "none")
    field = None if field == "none" else field
    if (field or arguments.vectors) and not with_fluid:
        asked = f"--field {field}" if field else "--vectors"
        raise CaseError(f"render: {asked}: {run.path} holds no cell fields (the run solved no fluid)")
    chosen = run.select(arguments.times, arguments.every)
    view = VIEWS[arguments.plane]
    normal = run.vertices[:, view.normal]
    plane_at = 0.5 * (normal.min() + normal.max()) if arguments.at is None else arguments.at
    if not normal.min() <= plane_at <= normal.max():
        raise CaseError(f"render: --at {plane_at:g}: outside the domain, whose {view.normal_name} "
                        f"runs from {normal.min():g} to {normal.max():g} m")
    folder = arguments.out or arguments.output_dir / "pictures"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise CaseError(f"render: --out {folder}: cannot make the folder: {error.strerror}") from None

    outline = domain_outline(run.vertices, run.cells, view)
    slice_cells, polygons = (slice_polygons(run.vertices, run.cells, view, plane_at)
                             if field or arguments.vectors else (np.zeros(0, int), None))
    if polygons is not None and len(slice_cells) == 0:
        raise CaseError(f"render: --at {plane_at:g}: the plane {view.normal_name} = {plane_at:g} m cuts no cell")
    frames = [read_frame(run, index, slice_cells, field, arguments.vectors) for index in chosen]
    field_limits = colour_limits([f.slice_values for f in frames], robust=field == "pressure")
    by_radius = arguments.particle_colour == "radius"
    particle_limits = colour_limits([f.radius if by_radius else np.linalg.norm(f.velocity, axis=1) for f in frames],
                                    robust=False, from_zero=not by_radius)
    size = arguments.size or default_size(picture_limits(outline),
                                          (field is not None) + any(len(f.radius) for f in frames))
    options = argparse.Namespace(**{**vars(arguments), "field": field, "size": tuple(size)})
    written = []
    for index, frame in zip(chosen, frames):
        at = "" if arguments.at is None else f"{arguments.at:g}"   # a plane asked for names its pictures
        stem = f"{field or 'particles'}_{arguments.plane}{at}_{index:06d}"
        picture = render_frame(frame, run, view, plane_at, polygons, outline, options, field_limits,
                               particle_limits, new_picture_path(folder, stem))
        print(f"{picture.path}  t = {frame.time:.6g} s", flush=True)
        written.append(picture)
    return written


def main(argv: list[str]) -> int:
    """``pmpm render ...``: exit status 0, or 2 with one line on stderr for bad input."""
    try:
        render(parse_render_arguments(argv))
        return 0
    except SystemExit as exit_request:  # --help
        return int(exit_request.code or 0)
    except CaseError as error:
        print(f"pmpm: error: {error}", file=sys.stderr, flush=True)
        return error.exit_status
