"""Immersed rigid bodies of prescribed motion (``[[body]]``): a paddle, a plate, an impeller.

A body is a solid inside the flow mesh, not a hole in it: the fluid in the cells it covers is
driven to its rigid motion by the same forcing as the particles' (``pmpm.coupling``), and
particles collide with its surface, a set of rigid moving wall triangles (``pmpm.collisions``).
Its motion is prescribed: a translation V and a rotation Ω about ``rotation_center`` (which moves
with the translation), so a point at x₀ at t = 0 is at

    x(t) = c + V t + R(Ω t) (x₀ − c),      moving at V + Ω × (x(t) − c − V t).

Shapes: an axis-aligned box, a cylinder, or a closed triangulated surface read from a file (its
inside by the generalised winding number). Everything here is geometry; the time loop asks for
the body's volume fraction in the cells it covers and its velocity there.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .arrays import rotation_matrix
from .errors import CaseError
from .injection import cylinder_frame

CYLINDER_FACETS = 48   # sides of the polygon a cylinder's surface is made of, for the collisions


@dataclass(frozen=True)
class Body:
    """One [[body]] (SI). ``triangles`` (m, 3, 3): its surface at t = 0, wound so that the normals
    (b − a) × (c − a) point out of it; ``tilt`` (3, 3): the rotation a box or cylinder was turned by
    about its centre at t = 0."""

    name: str
    shape: str
    center: np.ndarray
    tilt: np.ndarray
    size: np.ndarray | None
    axis: np.ndarray
    radius: float | None
    length: float | None
    velocity: np.ndarray
    angular_velocity: np.ndarray
    rotation_center: np.ndarray
    triangles: np.ndarray
    restitution: float | None = None
    friction: float | None = None
    rolling_friction: float | None = None

    # -- motion ---------------------------------------------------------------------------------
    @property
    def moves(self) -> bool:
        return bool(np.any(self.velocity) or np.any(self.angular_velocity))

    def to_start(self, points: np.ndarray, time: float) -> np.ndarray:
        """(k, 3) where the body's points that are at ``points`` at ``time`` were at t = 0."""
        turn = rotation_matrix(self.angular_velocity * time)
        return self.rotation_center + (points - self.rotation_center - self.velocity * time) @ turn

    def from_start(self, points: np.ndarray, time: float) -> np.ndarray:
        """(k, 3) where the body's points at ``points`` at t = 0 are at ``time``."""
        turn = rotation_matrix(self.angular_velocity * time)
        return self.rotation_center + self.velocity * time + (points - self.rotation_center) @ turn.T

    def velocity_at(self, points: np.ndarray, time: float) -> np.ndarray:
        """(k, 3) the body's velocity at ``points`` (m/s) at ``time``."""
        return self.velocity + np.cross(self.angular_velocity, points - self.rotation_center - self.velocity * time)

    def bounding_sphere(self, time: float) -> tuple[np.ndarray, float]:
        """A sphere (centre, radius) holding the body at ``time``."""
        corners = self.triangles.reshape(-1, 3)
        middle = 0.5 * (corners.min(axis=0) + corners.max(axis=0))
        return self.from_start(middle[None], time)[0], float(np.linalg.norm(corners - middle, axis=1).max())

    # -- inside -----------------------------------------------------------------------------------
    def local(self, points: np.ndarray, time: float) -> np.ndarray:
        """(k, 3) the points at ``time`` in the frame of the untilted shape at t = 0 (a rigid map)."""
        return (self.to_start(np.asarray(points, float).reshape(-1, 3), time) - self.center) @ self.tilt

    def inside(self, points: np.ndarray, time: float) -> np.ndarray:
        """(k,) bool: the points lie in the body at ``time`` (its surface included)."""
        if self.shape == "surface":
            return winding_number(self.to_start(np.asarray(points, float).reshape(-1, 3), time), self.triangles) > 0.5
        local = self.local(points, time)
        if self.shape == "box":
            return np.all(np.abs(local) <= 0.5 * self.size * (1 + 1e-12), axis=1)
        along = local @ self.axis
        across = np.linalg.norm(local - along[:, None] * self.axis, axis=1)
        return (np.abs(along) <= 0.5 * self.length * (1 + 1e-12)) & (across <= self.radius * (1 + 1e-12))

    def signed_distance(self, points: np.ndarray, time: float) -> np.ndarray | None:
        """(k,) the distance from each point to a box's or cylinder's surface, positive inside (m);
        None for a surface from a file."""
        if self.shape == "surface":
            return None
        local = self.local(points, time)
        if self.shape == "box":
            excess = np.abs(local) - 0.5 * self.size
        else:
            along = local @ self.axis
            across = np.linalg.norm(local - along[:, None] * self.axis, axis=1)
            excess = np.column_stack([np.abs(along) - 0.5 * self.length, across - self.radius])
        return -np.linalg.norm(np.maximum(excess, 0.0), axis=1) - np.minimum(excess.max(axis=1), 0.0)

    def covered_cells(self, mesh, time: float, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Local. The owned cells the body covers at ``time`` and its volume fraction in each, the
        share of the cells' sample points (``samples``: (s, n_vertices) weights, as
        ``coupling.locate.reference_samples``) inside it. Only the cells a box's or cylinder's
        surface may cut are sampled: a cell whose centre lies deeper inside than its farthest
        corner is covered whole, one farther outside not at all."""
        centre, radius = self.bounding_sphere(time)
        n_owned = mesh.n_owned_cells
        corners = mesh.vertex_xyz[mesh.cell_vertices[:n_owned]]
        reach = np.linalg.norm(corners - mesh.cell_center[:n_owned, None], axis=2).max(axis=1)
        near = np.flatnonzero(np.linalg.norm(mesh.cell_center[:n_owned] - centre, axis=1) <= radius + reach)
        alpha = np.ones(len(near))
        cut = np.arange(len(near))
        depth = self.signed_distance(mesh.cell_center[near], time)
        if depth is not None:
            alpha[depth < -reach[near]] = 0.0
            cut = np.flatnonzero(np.abs(depth) <= reach[near])
        if len(cut):
            points = np.matmul(samples, corners[near[cut]])          # (cut cells, samples, 3)
            alpha[cut] = self.inside(points.reshape(-1, 3), time).reshape(len(cut), -1).mean(axis=1)
        keep = alpha > 0
        return near[keep], alpha[keep]


def winding_number(points: np.ndarray, triangles: np.ndarray, chunk: int = 2_000_000) -> np.ndarray:
    """(k,) the generalised winding number of a closed surface of outward-wound ``triangles``
    (m, 3, 3) around each point: 1 inside, 0 outside (the solid angles the triangles subtend,
    Van Oosterom & Strackee 1983, over 4π)."""
    total = np.zeros(len(points))
    step = max(1, chunk // max(1, len(triangles)))
    for start in range(0, len(points), step):
        p = points[start:start + step, None, None, :]
        r = triangles[None] - p                                  # (k, m, 3, 3)
        length = np.linalg.norm(r, axis=3)
        a, b, c = r[:, :, 0], r[:, :, 1], r[:, :, 2]
        la, lb, lc = length[:, :, 0], length[:, :, 1], length[:, :, 2]
        numerator = np.einsum("kmi,kmi->km", a, np.cross(b, c))
        denominator = (la * lb * lc + np.einsum("kmi,kmi->km", a, b) * lc + np.einsum("kmi,kmi->km", b, c) * la
                       + np.einsum("kmi,kmi->km", c, a) * lb)
        total[start:start + step] = 2 * np.arctan2(numerator, denominator).sum(axis=1) / (4 * np.pi)
    return total


# -- building -------------------------------------------------------------------------------------
def box_triangles(center, size) -> np.ndarray:
    """(12, 3, 3) the faces of an axis-aligned box, wound outwards."""
    corner = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5) for k in (-0.5, 0.5)]) * size + center
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = [[corner[q[0]], corner[q[1]], corner[q[2]]] for q in quads] + \
                [[corner[q[0]], corner[q[2]], corner[q[3]]] for q in quads]
    return outward(np.array(triangles), np.asarray(center, float))


def cylinder_triangles(center, axis, radius, length, facets: int = CYLINDER_FACETS) -> np.ndarray:
    """(4 facets, 3, 3) a cylinder's side and end caps as a closed polyhedron, wound outwards. The
    polygon's vertices lie on the circle; its mid-sides at radius r cos(π/facets)."""
    e1, e2, axis = cylinder_frame(axis)
    angle = 2 * np.pi * np.arange(facets) / facets
    ring = radius * (np.cos(angle)[:, None] * e1 + np.sin(angle)[:, None] * e2)
    bottom, top = center - 0.5 * length * axis + ring, center + 0.5 * length * axis + ring
    after = np.roll(np.arange(facets), -1)
    ends = (np.broadcast_to(center - 0.5 * length * axis, (facets, 3)), np.broadcast_to(center + 0.5 * length * axis,
                                                                                        (facets, 3)))
    triangles = np.concatenate([np.stack([bottom, bottom[after], top[after]], axis=1),
                                np.stack([bottom, top[after], top], axis=1),
                                np.stack([ends[0], bottom[after], bottom], axis=1),
                                np.stack([ends[1], top, top[after]], axis=1)])
    return outward(triangles, np.asarray(center, float))


def outward(triangles: np.ndarray, inner_point: np.ndarray) -> np.ndarray:
    """The triangles of a convex polyhedron wound so that each normal points away from a point
    inside it."""
    normal = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    flip = np.einsum("ij,ij->i", normal, triangles.mean(axis=1) - inner_point) < 0
    triangles = triangles.copy()
    triangles[flip] = triangles[flip][:, [0, 2, 1]]
    return triangles


def read_surface(path) -> np.ndarray:
    """(m, 3, 3) the triangles of a closed surface file, wound outwards (by its signed volume)."""
    import meshio
    if not path.is_file():
        raise CaseError(f"{path}: surface file not found")
    try:
        surface = meshio.read(path)
    except Exception as error:   # meshio raises many kinds for a file that is not a surface
        raise CaseError(f"{path}: not a surface meshio can read ({error})") from None
    triangles = [surface.points[block.data] for block in surface.cells if block.type == "triangle"]
    if not triangles:
        raise CaseError(f"{path}: holds no triangles (a closed triangulated surface is needed)")
    triangles = np.concatenate(triangles).astype(float)
    volume = np.einsum("ij,ij->i", triangles[:, 0], np.cross(triangles[:, 1], triangles[:, 2])).sum() / 6
    if abs(volume) <= 1e-12 * np.ptp(triangles.reshape(-1, 3), axis=0).prod():
        raise CaseError(f"{path}: the surface encloses no volume (it must be closed)")
    return triangles if volume > 0 else triangles[:, [0, 2, 1]]


def build_bodies(case) -> tuple[Body, ...]:
    """The case's [[body]] tables."""
    bodies = []
    for i, section in enumerate(case.bodies):
        center = np.asarray(section.center, float)
        axis = np.asarray(section.axis, float) / np.linalg.norm(section.axis)
        size = np.asarray(section.size, float) if section.size is not None else None
        tilt = rotation_matrix(np.asarray(section.tilt, float))
        if section.shape == "box":
            triangles = center + (box_triangles(np.zeros(3), size) @ tilt.T)
        elif section.shape == "cylinder":
            triangles = center + (cylinder_triangles(np.zeros(3), axis, section.radius, section.length) @ tilt.T)
        else:
            triangles = read_surface(case.resolve(section.file))
        bodies.append(Body(section.name or f"body {i}", section.shape, center, tilt, size, axis, section.radius,
                           section.length, np.asarray(section.velocity, float),
                           np.asarray(section.angular_velocity, float), np.asarray(section.rotation_center, float),
                           triangles, section.restitution, section.friction, section.rolling_friction))
    return tuple(bodies)
