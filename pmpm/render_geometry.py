"""Geometry of a picture (``pmpm render``): the orthographic view, the domain's outline, the
polygons where a plane cuts the cells, and spheres rasterised per pixel with depth and shading.

Pure numpy over whole arrays of cells, faces, edges and particles; no matplotlib here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Faces of a VTK hexahedron (bottom 0-1-2-3, top 4-5-6-7) and tetrahedron; orientation is not
# relied on: normals are turned to point away from the cell's centre.
CELL_FACES = {8: np.array([[0, 1, 2, 3], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]),
              4: np.array([[0, 1, 2], [0, 1, 3], [1, 2, 3], [0, 2, 3]])}
CELL_EDGES = {8: np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                           [0, 4], [1, 5], [2, 6], [3, 7]]),
              4: np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])}
FEATURE_ANGLE = np.radians(30.0)   # boundary edges sharper than this are drawn (a box's 12 edges)
LIGHT = np.array([-0.45, 0.55, 1.0]) / np.linalg.norm([-0.45, 0.55, 1.0])   # from the upper left, front
AMBIENT, HIGHLIGHT, SHININESS = 0.38, 0.55, 30.0


@dataclass(frozen=True)
class View:
    """An orthographic view along a coordinate axis, right-handed: right × up points at the viewer.

    Attributes
    ----------
    normal, right, up : int
        Coordinate index of the viewing axis (the slice's normal), of the picture's horizontal and
        vertical axes.
    toward_viewer : float
        +1 if the viewer sits on the +normal side, -1 otherwise.
    """

    normal: int
    right: int
    up: int
    toward_viewer: float

    @property
    def normal_name(self) -> str:
        return "xyz"[self.normal]

    @property
    def right_name(self) -> str:
        return "xyz"[self.right]

    @property
    def up_name(self) -> str:
        return "xyz"[self.up]

    @property
    def looking(self) -> str:
        return f"{'-' if self.toward_viewer > 0 else '+'}{self.normal_name}"

    def project(self, points: np.ndarray) -> np.ndarray:
        """Picture coordinates (right, up) in metres of points (..., 3)."""
        return points[..., [self.right, self.up]]

    def nearness(self, points: np.ndarray) -> np.ndarray:
        """Distance toward the viewer (m) of points (..., 3): larger is nearer."""
        return self.toward_viewer * points[..., self.normal]

    def nearness_of(self, coordinate: float) -> float:
        """Nearness (m) of the plane at ``coordinate`` along the normal."""
        return self.toward_viewer * coordinate


VIEWS = {"x": View(0, 1, 2, +1.0), "y": View(1, 0, 2, -1.0), "z": View(2, 0, 1, +1.0)}


def domain_outline(vertices: np.ndarray, cells: np.ndarray, view: View) -> np.ndarray:
    """The domain's outline as seen in ``view``: its boundary's feature and silhouette edges.

    A boundary face is a cell face no other cell shares. Of the boundary's edges, those drawn are
    sharp (the two faces' normals differ by more than ``FEATURE_ANGLE``), on the silhouette (one
    face turned toward the viewer, the other not), or shared by other than two boundary faces.

    Parameters
    ----------
    vertices : ndarray, shape (n_vertices, 3)
        Vertex coordinates (m).
    cells : ndarray, shape (n_cells, 8) or (n_cells, 4)
        Hexahedra or tetrahedra, VTK vertex order.
    view : View

    Returns
    -------
    ndarray, shape (n_edges, 2, 2)
        Projected edge end points (m).
    """
    pattern = CELL_FACES[cells.shape[1]]
    faces = cells[:, pattern].reshape(-1, pattern.shape[1])
    owner = np.repeat(np.arange(len(cells)), len(pattern))
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])
    same_as_next = np.all(key[order][1:] == key[order][:-1], axis=1)
    shared = np.zeros(len(faces), bool)
    shared[order[1:][same_as_next]] = shared[order[:-1][same_as_next]] = True
    boundary, boundary_owner = faces[~shared], owner[~shared]

    corners = vertices[boundary]
    if boundary.shape[1] == 4:
        normal = np.cross(corners[:, 2] - corners[:, 0], corners[:, 3] - corners[:, 1])
    else:
        normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    outward = corners.mean(axis=1) - vertices[cells[boundary_owner]].mean(axis=1)
    normal *= np.sign(np.einsum("fi,fi->f", normal, outward))[:, None]
    normal /= np.maximum(np.linalg.norm(normal, axis=1), 1e-300)[:, None]

    k = boundary.shape[1]
    edges = np.stack([boundary, np.roll(boundary, -1, axis=1)], axis=2).reshape(-1, 2)
    edge_face = np.repeat(np.arange(len(boundary)), k)
    edge_key = np.sort(edges, axis=1)
    order = np.lexsort(edge_key.T[::-1])
    sorted_key = edge_key[order]
    starts = np.flatnonzero(np.r_[True, np.any(sorted_key[1:] != sorted_key[:-1], axis=1)])
    counts = np.diff(np.r_[starts, len(order)])
    first_face = edge_face[order[starts]]
    second_face = edge_face[order[np.minimum(starts + 1, len(order) - 1)]]
    cosine = np.einsum("ei,ei->e", normal[first_face], normal[second_face])
    facing = np.sign(np.round(view.toward_viewer * normal[:, view.normal], 9))
    drawn = ((counts != 2) | (cosine < np.cos(FEATURE_ANGLE))
             | (facing[first_face] != facing[second_face]))
    return view.project(vertices[sorted_key[starts[drawn]]])


def slice_polygons(vertices: np.ndarray, cells: np.ndarray, view: View, at: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The polygons where the plane ``x[view.normal] = at`` cuts the cells.

    Each cut cell's polygon is the convex hull of the points where the plane crosses its edges,
    ordered by angle around their mean. A vertex exactly on the plane counts as below it, so a plane
    through a layer of faces takes the layer of cells above it, once (below it, if there is none
    above: the plane of the domain's top).

    Parameters
    ----------
    vertices : ndarray, shape (n_vertices, 3)
        Vertex coordinates (m).
    cells : ndarray, shape (n_cells, 8) or (n_cells, 4)
        Hexahedra or tetrahedra (convex cells).
    view : View
    at : float
        The plane's coordinate along the view's normal (m).

    Returns
    -------
    cut_cells : ndarray, shape (n_cut,)
        Indices of the cells cut.
    polygons : ndarray, shape (n_cut, n_edges_per_cell, 2)
        Each polygon's corners in picture coordinates (m), the last repeated to pad.
    """
    above = vertices[:, view.normal] > at
    cell_above = above[cells]
    cut_cells = np.flatnonzero(cell_above.any(axis=1) & ~cell_above.all(axis=1))
    if cut_cells.size == 0:
        above = vertices[:, view.normal] >= at
        cell_above = above[cells]
        cut_cells = np.flatnonzero(cell_above.any(axis=1) & ~cell_above.all(axis=1))
    edges = cells[cut_cells][:, CELL_EDGES[cells.shape[1]]]                 # (n_cut, n_edges, 2)
    start, end = vertices[edges[..., 0]], vertices[edges[..., 1]]
    crossing = above[edges[..., 0]] != above[edges[..., 1]]
    height_start = start[..., view.normal] - at
    height_end = end[..., view.normal] - at
    fraction = np.where(crossing, height_start / np.where(crossing, height_start - height_end, 1.0), 0.0)
    points = view.project(start + fraction[..., None] * (end - start))
    count = crossing.sum(axis=1)
    middle = (points * crossing[..., None]).sum(axis=1) / np.maximum(count, 1)[:, None]
    angle = np.arctan2(points[..., 1] - middle[:, 1, None], points[..., 0] - middle[:, 0, None])
    order = np.argsort(np.where(crossing, angle, np.inf), axis=1)
    order = np.take_along_axis(order, np.minimum(np.arange(order.shape[1]), count[:, None] - 1), axis=1)
    return cut_cells, np.take_along_axis(points, order[..., None], axis=1)


def arrow_points(polygons: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points of a square grid of ``spacing``, half a spacing in from the slice's lower-left
    corner, that lie in the slice, and the polygon holding each.

    Each polygon is tested against the 3 × 3 grid points around its centre, so polygons up to about
    two spacings across find all theirs.

    Parameters
    ----------
    polygons : ndarray, shape (n, k, 2)
        Convex polygons, corners counter-clockwise (as :func:`slice_polygons` gives them), in m.
    spacing : float
        Grid spacing (m).

    Returns
    -------
    points : ndarray, shape (m, 2)
        Grid points inside the slice (m).
    polygon : ndarray, shape (m,)
        Index of the polygon holding each point.
    """
    origin = polygons.reshape(-1, 2).min(axis=0) + 0.5 * spacing    # half a spacing clear of the edge
    nearest = np.round((polygons.mean(axis=1) - origin) / spacing).astype(np.int64)
    shifts = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1]), axis=-1).reshape(-1, 2)
    grid = nearest[:, None, :] + shifts                                       # (n, 9, 2)
    points = origin + grid * spacing
    edge = np.roll(polygons, -1, axis=1) - polygons                           # (n, k, 2)
    relative = points[:, :, None, :] - polygons[:, None, :, :]                # (n, 9, k, 2)
    cross = edge[:, None, :, 0] * relative[..., 1] - edge[:, None, :, 1] * relative[..., 0]
    tolerance = 1e-9 * spacing * spacing
    inside = np.all(cross >= -tolerance, axis=2)                              # (n, 9)
    polygon, which = np.nonzero(inside)
    key = grid[polygon, which]
    _, first = np.unique(key[:, 0] * (1 << 31) + key[:, 1], return_index=True)   # a point once
    return points[polygon[first], which[first]], polygon[first]


def shade_spheres(centre: np.ndarray, nearness: np.ndarray, radius: np.ndarray, colour: np.ndarray,
                  shape: tuple[int, int], split: float | None = None, chunk_pixels: int = 1_000_000):
    """Rasterise spheres into RGBA images, nearest surface per pixel, shaded.

    All lengths in pixels of the image. Each sphere covers the pixels whose centres lie within its
    radius of its centre; at each, its surface's nearness is ``nearness + sqrt(r² - d²)``, and the
    nearest surface wins (a z-buffer), so spheres that overlap or touch hide each other correctly.
    The colour is Lambert-shaded for a light from the upper left with a white highlight.

    Parameters
    ----------
    centre : ndarray, shape (n, 2)
        Sphere centres (pixels from the image's lower-left corner, x right, y up).
    nearness : ndarray, shape (n,)
        Distance of the centres toward the viewer (pixels).
    radius : ndarray, shape (n,)
        Radii (pixels).
    colour : ndarray, shape (n, 3)
        Base RGB colours in [0, 1].
    shape : (int, int)
        Image rows and columns; row 0 is the bottom.
    split : float, optional
        Nearness of an opaque plane: surface in front of it goes to the front image, the rest to
        the back one.
    chunk_pixels : int
        Candidate pixels handled at once (memory bound).

    Returns
    -------
    back, front : ndarray, shape (rows, columns, 4), or None
        Straight-alpha RGBA; ``back`` is None without ``split``.
    """
    rows, columns = shape
    layers = [_ZBuffer(rows, columns) for _ in range(1 if split is None else 2)]
    # Spheres of similar size share one square of candidate pixels, of half-width a power of two.
    size_class = np.ceil(np.log2(np.maximum(radius, 0.5) + 1.0)).astype(int)
    on_picture = np.all((centre + radius[:, None] > 0) & (centre - radius[:, None] < [columns, rows]), axis=1)
    view_direction = np.array([0.0, 0.0, 1.0])
    halfway = (LIGHT + view_direction) / np.linalg.norm(LIGHT + view_direction)
    for size in np.unique(size_class[on_picture]):
        members = np.flatnonzero(on_picture & (size_class == size))
        offsets = np.arange(-2 ** size, 2 ** size + 1)
        dx, dy = (o.ravel() for o in np.meshgrid(offsets, offsets))
        per_sphere = dx.size
        step = max(1, chunk_pixels // per_sphere)
        for first in range(0, len(members), step):
            sphere = members[first:first + step]
            column = np.floor(centre[sphere, 0])[:, None].astype(np.int64) + dx
            row = np.floor(centre[sphere, 1])[:, None].astype(np.int64) + dy
            across = column + 0.5 - centre[sphere, 0, None]
            upward = row + 0.5 - centre[sphere, 1, None]
            r = radius[sphere, None]
            inside = ((across ** 2 + upward ** 2 < r ** 2) & (column >= 0) & (column < columns)
                      & (row >= 0) & (row < rows))
            owner = np.broadcast_to(sphere[:, None], inside.shape)[inside]
            normal_x, normal_y = across[inside] / radius[owner], upward[inside] / radius[owner]
            normal_z = np.sqrt(np.maximum(1.0 - normal_x ** 2 - normal_y ** 2, 0.0))
            diffuse = np.maximum(normal_x * LIGHT[0] + normal_y * LIGHT[1] + normal_z * LIGHT[2], 0.0)
            shine = HIGHLIGHT * np.maximum(normal_x * halfway[0] + normal_y * halfway[1]
                                           + normal_z * halfway[2], 0.0) ** SHININESS
            rgb = colour[owner] * (AMBIENT + (1.0 - AMBIENT) * diffuse)[:, None]
            rgb = rgb * (1.0 - shine[:, None]) + shine[:, None]
            surface = nearness[owner] + radius[owner] * normal_z
            pixel = row[inside] * columns + column[inside]
            if split is None:
                layers[0].add(pixel, surface, rgb)
            else:
                in_front = surface > split
                layers[0].add(pixel[~in_front], surface[~in_front], rgb[~in_front])
                layers[1].add(pixel[in_front], surface[in_front], rgb[in_front])
    images = [layer.image() for layer in layers]
    return (None, images[0]) if split is None else (images[0], images[1])


class _ZBuffer:
    """Nearest surface per pixel: nearness and colour of the winner so far."""

    def __init__(self, rows: int, columns: int):
        self.shape = (rows, columns)
        self.nearness = np.full(rows * columns, -np.inf)
        self.rgb = np.zeros((rows * columns, 3))

    def add(self, pixel: np.ndarray, surface: np.ndarray, rgb: np.ndarray) -> None:
        """Offer candidate surfaces; per pixel the nearest, if nearer than the current one, wins."""
        if pixel.size == 0:
            return
        order = np.lexsort((surface, pixel))
        last_of_pixel = order[np.r_[pixel[order][1:] != pixel[order][:-1], True]]
        winner = last_of_pixel[surface[last_of_pixel] > self.nearness[pixel[last_of_pixel]]]
        self.nearness[pixel[winner]] = surface[winner]
        self.rgb[pixel[winner]] = rgb[winner]

    def image(self) -> np.ndarray:
        alpha = np.isfinite(self.nearness).astype(float)
        return np.concatenate([self.rgb, alpha[:, None]], axis=1).reshape(*self.shape, 4)
