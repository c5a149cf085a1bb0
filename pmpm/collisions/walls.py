"""Wall triangles: geometry, coefficients and motion; the search for triangles near points.

A wall is any mesh boundary of type "wall" (or not listed in the case): its faces, split into
triangles with the normal into the domain. Each triangle carries its restitution, friction,
rolling friction, its velocity V and angular velocity Ω about ``center`` (the wall velocity at a
point p is V + Ω × (p − center)), whether it moves rigidly (a paddle: the triangle itself moves)
or only its surface moves (a conveyor, a lid: the triangle stays), and whether particles that
touch it are deposited. A ``Walls`` is not changed after it is built: a rigid wall that moved is
a new ``Walls`` (``moved``), so what is cached on one (its search grid) stays true.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from ..arrays import cross, rotate
from .settings import (DEFAULT_FRICTION, DEFAULT_RESTITUTION, DEFAULT_ROLLING_FRICTION,
                       collision_coefficients)


@dataclass(frozen=True, eq=False)
class Walls:
    """Planar wall triangles (SI), each with its own coefficients and motion.

    ``a, b, c`` vertices and ``normal`` (unit, into the domain) are (m, 3); ``boundary`` (m,) the
    boundary index; ``restitution``, ``friction``, ``rolling_friction`` (m,); ``velocity`` (m/s),
    ``angular_velocity`` (rad/s) and ``center`` (m) (m, 3) give the wall velocity
    V + Ω × (p − center) at a point p; ``rigid`` (m,) bool: the triangle itself moves (a paddle) —
    else only its surface moves (a conveyor, a lid); ``deposition`` (m,) bool: particles stick.
    Fields are not reassigned after construction (a moved wall is a new object, see ``moved``).
    """

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    normal: np.ndarray
    boundary: np.ndarray
    restitution: np.ndarray
    friction: np.ndarray
    rolling_friction: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    center: np.ndarray
    rigid: np.ndarray
    deposition: np.ndarray
    names: tuple = ()  # boundary names, indexed by ``boundary``

    def __len__(self) -> int:
        return len(self.boundary)

    @classmethod
    def from_triangles(cls, triangles, normal=None, boundary=None, restitution=DEFAULT_RESTITUTION,
                       friction=DEFAULT_FRICTION, rolling_friction=DEFAULT_ROLLING_FRICTION,
                       velocity=(0.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, 0.0), center=(0.0, 0.0, 0.0),
                       rigid=False, deposition=False, names=()) -> "Walls":
        """Walls from (m, 3, 3) vertices; scalars and 3-vectors are broadcast to every triangle.

        Without ``normal``, the normal follows the winding: (b − a) × (c − a), normalised.
        """
        tri = np.asarray(triangles, float).reshape(-1, 3, 3)
        m = len(tri)
        a, b, c = tri[:, 0].copy(), tri[:, 1].copy(), tri[:, 2].copy()
        if normal is None:
            normal = cross(b - a, c - a)
        normal = np.broadcast_to(np.asarray(normal, float), (m, 3))
        normal = normal / np.linalg.norm(normal, axis=1, keepdims=True)

        def per(value, shape, dtype=float):
            return np.array(np.broadcast_to(np.asarray(value, dtype), (m, *shape)))

        return cls(a, b, c, normal.copy(), per(0 if boundary is None else boundary, (), np.int64),
                   per(restitution, ()), per(friction, ()), per(rolling_friction, ()),
                   per(velocity, (3,)), per(angular_velocity, (3,)), per(center, (3,)),
                   per(rigid, (), bool), per(deposition, (), bool), tuple(names))

    # -- motion -----------------------------------------------------------------------------------
    @cached_property
    def moves(self) -> np.ndarray:
        """(m,) bool: rigid triangles with a velocity or an angular velocity."""
        return self.rigid & self.drives

    @cached_property
    def drives(self) -> np.ndarray:
        """(m,) bool: triangles that can put energy into a contact, with a velocity or an angular
        velocity (rigid or not: a belt's surface moves too)."""
        return self.velocity.any(1) | self.angular_velocity.any(1)

    def moved(self, dt: float) -> "Walls":
        """The walls after ``dt``: rigid triangles rotated by Ω dt about their centre (Rodrigues) and
        translated by V dt, their centres translated; ``self`` if none moves."""
        k = np.flatnonzero(self.moves)
        if len(k) == 0:
            return self
        theta = self.angular_velocity[k] * dt
        shift = self.velocity[k] * dt
        centre = self.center[k]
        a, b, c, normal, center = (array.copy() for array in (self.a, self.b, self.c, self.normal, self.center))
        for moved, old in ((a, self.a), (b, self.b), (c, self.c)):
            moved[k] = rotate(old[k] - centre, theta) + centre + shift
        normal[k] = rotate(self.normal[k], theta)
        center[k] = centre + shift
        return replace(self, a=a, b=b, c=c, normal=normal, center=center)

    @cached_property
    def top_speed(self) -> np.ndarray:
        """(m,) the largest speed of a point of each triangle (m/s): |V| + |Ω| arm for moving rigid
        triangles, arm the farthest vertex from the centre; 0 for the others."""
        arm = np.max([np.linalg.norm(v - self.center, axis=1) for v in (self.a, self.b, self.c)], axis=0)
        speed = np.linalg.norm(self.velocity, axis=1) + np.linalg.norm(self.angular_velocity, axis=1) * arm
        return np.where(self.moves, speed, 0.0)

    def travel(self, dt: float) -> np.ndarray:
        """(m,) the farthest any point of each triangle moves in ``dt`` (m)."""
        return self.top_speed * dt

    @cached_property
    def kernel_arrays(self) -> tuple:
        """The arrays in the order the compiled kernels take them (``narrow``): a, b, c, normal,
        center, velocity, angular_velocity (float64), rigid, moves, deposition (bool)."""
        arrays = (self.a, self.b, self.c, self.normal, self.center, self.velocity, self.angular_velocity)
        return tuple(np.ascontiguousarray(a, float) for a in arrays) + tuple(
            np.ascontiguousarray(a, np.bool_) for a in (self.rigid, self.moves, self.deposition))

    # -- search -----------------------------------------------------------------------------------
    @cached_property
    def centroid(self) -> np.ndarray:
        """(m, 3) triangle centroids (m)."""
        return (self.a + self.b + self.c) / 3.0

    @cached_property
    def bounding_radius(self) -> np.ndarray:
        """(m,) distance from each centroid to its farthest vertex (m)."""
        return np.max([np.linalg.norm(v - self.centroid, axis=1) for v in (self.a, self.b, self.c)], axis=0)

    @cached_property
    def grids(self) -> dict:
        """The grids built so far (``grid``), by cell size in median triangle radii; a new
        ``Walls`` starts without any."""
        return {}

    def grid(self, reach: float = 0.0) -> tuple:
        """A uniform grid of the triangles (``wall_grid``) for queries reaching up to ``reach`` (m):
        (lower corner (3,), cell size (m), cells per axis (3,), CSR start, triangle indices). Cells
        of the median triangle's bounding radius R where the reach is within R (a point near a wall
        visits few triangles), else of 2 R (a long reach visits few cells); at most 64 per axis."""
        radius = self.median_radius
        size = 1.0 if reach <= radius else 2.0
        if size not in self.grids:
            from .jit import kernels
            lower = np.min([self.a.min(0), self.b.min(0), self.c.min(0)], axis=0)
            upper = np.max([self.a.max(0), self.b.max(0), self.c.max(0)], axis=0)
            cell = max(size * radius, float((upper - lower).max()) / 64.0, 1e-12)
            dims = np.maximum(np.ceil((upper - lower) / cell).astype(np.int64), 1)
            start, items = kernels().wall_grid.build(self.a, self.b, self.c, lower, cell, dims)
            self.grids[size] = (lower, cell, dims, start, items)
        return self.grids[size]

    @cached_property
    def median_radius(self) -> float:
        """The median of the triangles' bounding radii (m)."""
        return float(np.median(self.bounding_radius))

    @cached_property
    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """(m, 3) lower and upper corners of each triangle's bounding box (m)."""
        return (np.minimum(np.minimum(self.a, self.b), self.c), np.maximum(np.maximum(self.a, self.b), self.c))

    def near(self, points: np.ndarray, reach, extra=None) -> tuple[np.ndarray, np.ndarray]:
        """(point, triangle) index pairs that may come within ``reach`` (m; a scalar or one per
        point) of each other when the triangle moves by up to ``extra`` (per triangle, m; e.g. its
        travel in a step): the triangle's bounding box grown by reach + extra holds the point, and
        |p − centroid| <= reach + bounding radius + extra. Sorted by point, then triangle."""
        none = np.zeros(0, np.int64)
        if len(points) == 0 or len(self) == 0:
            return none, none
        from .jit import kernels
        reach = np.ascontiguousarray(np.broadcast_to(np.asarray(reach, float), len(points)))
        extra = np.zeros(len(self)) if extra is None else np.ascontiguousarray(extra, float)
        lower, cell, dims, start, items = self.grid(float(reach.max()) + float(extra.max()))
        return kernels().wall_grid.near(np.ascontiguousarray(points, float), reach, extra, float(extra.max()),
                                        lower, cell, dims, start, items, *self.box, self.centroid,
                                        self.bounding_radius)


def closest_points_on_triangles(p, a, b, c) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of each triangle (a, b, c) to each point p, all (k, 3).

    Returns the points (k, 3) and a (k,) bool, true where the closest point is inside the face
    (not on an edge or a vertex). Voronoi regions of the vertices, edges and face in turn
    (the compiled ``contact_times.closest_on_triangle`` is the same algorithm for one point).
    """
    ab, ac, ap = b - a, c - a, p - a
    bp, cp = p - b, p - c
    d1, d2 = np.sum(ab * ap, 1), np.sum(ac * ap, 1)
    d3, d4 = np.sum(ab * bp, 1), np.sum(ac * bp, 1)
    d5, d6 = np.sum(ab * cp, 1), np.sum(ac * cp, 1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        s_ab = d1 / (d1 - d3)
        s_ac = d2 / (d2 - d6)
        s_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        total = va + vb + vc
        v, w = vb / total, vc / total
    in_a = (d1 <= 0) & (d2 <= 0)
    in_b = (d3 >= 0) & (d4 <= d3)
    on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    in_c = (d6 >= 0) & (d5 <= d6)
    on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    regions = [in_a, in_b, on_ab, in_c, on_ac, on_bc]
    points = [a, b, a + s_ab[:, None] * ab, c, a + s_ac[:, None] * ac, b + s_bc[:, None] * (c - b)]
    face = ~np.any(regions, axis=0)
    q = a + v[:, None] * ab + w[:, None] * ac
    for region, point in zip(regions[::-1], points[::-1]):  # the first true region wins
        q = np.where(region[:, None], point, q)
    return q, face


def wall_distances(x: np.ndarray, walls: Walls, reach) -> np.ndarray:
    """(n,) distance from each point to the nearest wall triangle within ``reach`` (inf beyond)."""
    p, k = walls.near(x, reach)
    out = np.full(len(x), np.inf)
    if len(p):
        q, _ = closest_points_on_triangles(x[p], walls.a[k], walls.b[k], walls.c[k])
        d = np.linalg.norm(x[p] - q, axis=1)
        order = np.lexsort((d, p))  # nearest first within each point
        first = np.ones(len(p), bool)
        first[1:] = p[order][1:] != p[order][:-1]
        out[p[order][first]] = d[order][first]
    return out


def build_walls(case, mesh, bodies=()) -> Walls:
    """Collective. The wall triangles of the case's mesh and of its immersed bodies, with their
    coefficients and motion.

    The boundaries particles meet as walls (``particles_bounce``): walls (listed or not), inlets (a
    distributor plate) and symmetry planes, unless ``particles = "pass"``; outlets only with
    ``particles = "wall"``. Coefficients default to [collisions] (or 0.9 / 0.3 / 0.0 without it);
    [deposition] zones name the walls where particles stick. Only a wall's own motion moves it
    (an inlet's velocity is the fluid's). Each body (``pmpm.bodies.Body``) adds its surface as
    rigid triangles moving with it, after the mesh's boundaries in ``names``.
    """
    names = [name for name in mesh.boundary_names if particles_bounce(case.boundaries.get(name))]
    triangles, boundary, normal = mesh.boundary_triangles(names)
    walls = Walls.from_triangles(np.reshape(triangles, (-1, 3, 3)), normal=np.reshape(normal, (-1, 3)),
                                 boundary=boundary, names=tuple(mesh.boundary_names))
    defaults = collision_coefficients(case)
    zones = set(case.deposition.zones) if case.deposition is not None else set()
    for index, name in enumerate(mesh.boundary_names):
        rows = walls.boundary == index
        if not rows.any():
            continue
        section = case.boundaries.get(name)
        for key in ("restitution", "friction", "rolling_friction"):
            value = getattr(section, key) if section is not None else None
            getattr(walls, key)[rows] = defaults[key] if value is None else value
        if section is not None and section.type == "wall":
            walls.velocity[rows] = section.velocity
            walls.angular_velocity[rows] = section.angular_velocity
            walls.center[rows] = section.center
            walls.rigid[rows] = section.motion == "rigid"
        walls.deposition[rows] = name in zones
    return with_bodies(walls, bodies, defaults, zones)


def with_bodies(walls: Walls, bodies, defaults: dict, zones=frozenset()) -> Walls:
    """``walls`` and the surfaces of ``bodies`` (at t = 0, wound outwards: the normal points to the
    particles' side), each a rigid wall moving as its body: V, and Ω about its rotation centre."""
    if not bodies:
        return walls
    first = len(walls.names)
    parts = [walls]
    for index, body in enumerate(bodies):
        coefficients = {key: defaults[key] if getattr(body, key) is None else getattr(body, key)
                        for key in ("restitution", "friction", "rolling_friction")}
        parts.append(Walls.from_triangles(body.triangles, boundary=first + index, velocity=body.velocity,
                                          angular_velocity=body.angular_velocity, center=body.rotation_center,
                                          rigid=True, deposition=body.name in zones, **coefficients))
    fields = {name: np.concatenate([getattr(part, name) for part in parts])
              for name in ("a", "b", "c", "normal", "boundary", "restitution", "friction", "rolling_friction",
                           "velocity", "angular_velocity", "center", "rigid", "deposition")}
    return Walls(**fields, names=walls.names + tuple(body.name for body in bodies))


def particles_bounce(section) -> bool:
    """Whether particles meet a boundary (its case section, None: an unlisted wall) as a wall."""
    if section is None:
        return True
    choice = getattr(section, "particles", None)
    if choice is not None:
        return choice == "wall"
    return section.type != "outlet"
