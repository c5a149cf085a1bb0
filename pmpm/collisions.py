"""Hard-sphere collisions resolved in time order (paper eq. 3-8), walls, deposition.

Velocities are constant inside a step (the caller has already applied gravity, drag and field
forces as a velocity update), so a contact is found from kinematics alone: two spheres touch when
|Δx + Δv t| = r_i + r_j (eq. 5-7), a sphere touches a wall triangle when its distance to the
closest point of the triangle (face, edge or vertex) reaches r. The step is an event loop: the
earliest contact is resolved (everything moves to it, eq. 8; an impulse with normal restitution e
and Coulomb friction μ is applied), the next contacts of the particles it changed are recomputed,
and so on until the end of the step.

Impulse at a contact with unit normal n (towards particle i) and relative contact velocity u
(u_n = u·n < 0 approaching)::

    J_n = -(1 + e) u_n / (1/m_i + 1/m_j)
    J_t = -u_t / k_t,  k_t = 1/m_i + r_i²/I_i + 1/m_j + r_j²/I_j   (stops sliding: 2/7 m* u_t for spheres)
    |J_t| <= μ J_n, else J_t = -μ J_n û_t (sliding)
    Δv_i = J/m_i,  Δω_i = (a_i × J)/I_i  with a_i = -r_i n the arm to the contact point

Fixed, prescribed and deposited particles and walls have infinite mass. A contact approaching
slower than ``rest_speed`` (of the order of |g| dt) is made inelastic, so resting contacts come to
rest instead of bouncing with ever smaller, ever more frequent bounces.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from .errors import CaseError
from .particles import FIXED, FREE, ParticleState

DEFAULT_RESTITUTION, DEFAULT_FRICTION, DEFAULT_ROLLING_FRICTION = 0.9, 0.3, 0.0
APPROACH_TOL = 1e-9   # relative: approach speeds below 1e-9 |u| are round-off, not contacts
TOUCH_TOL = 1e-9      # relative: spheres this close count as touching
CONTACT_TOL = 1e-6    # relative: resting contacts are those this close at the start of a step
GAP_TOL = 1e-7        # relative to the radius: a predicted wall contact further than this is rescheduled


# ----------------------------------------------------------------------------------------------
# Walls
# ----------------------------------------------------------------------------------------------
@dataclass
class Walls:
    """Planar wall triangles (SI), each with its own coefficients and motion.

    ``a, b, c`` vertices and ``normal`` (unit, into the domain) are (m, 3); ``boundary`` (m,) the
    boundary index; ``restitution``, ``friction``, ``rolling_friction`` (m,); ``velocity`` (m/s),
    ``angular_velocity`` (rad/s) and ``center`` (m) (m, 3) give the wall velocity
    V + Ω × (p − center) at a point p; ``rigid`` (m,) bool: the triangle itself moves (a paddle) —
    else only its surface moves (a conveyor, a lid); ``deposition`` (m,) bool: particles stick.
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
    _search: tuple | None = field(default=None, init=False, repr=False, compare=False)

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

    @property
    def moves(self) -> np.ndarray:
        """(m,) bool: rigid triangles that actually move."""
        return self.moving(slice(None))

    def moving(self, k) -> np.ndarray:
        """Bool per triangle of ``k``: rigid and with a velocity or an angular velocity."""
        return self.rigid[k] & (self.velocity[k].any(-1) | self.angular_velocity[k].any(-1))

    def geometry_at(self, k: np.ndarray, t) -> tuple:
        """Vertices, normal and rotation centre of triangles ``k`` at time ``t`` into the step.

        Rigid triangles rotate by Ω t about their centre (Rodrigues) and translate by V t.
        """
        a, b, c, n, ctr = self.a[k], self.b[k], self.c[k], self.normal[k], self.center[k]
        moving = self.moving(k)
        if not moving.any():
            return a, b, c, n, ctr
        t = np.broadcast_to(np.asarray(t, float), k.shape)[moving]
        rotate = rodrigues(self.angular_velocity[k][moving], t)
        shift = self.velocity[k][moving] * t[:, None]
        centre = ctr[moving]
        a, b, c, n, ctr = a.copy(), b.copy(), c.copy(), n.copy(), ctr.copy()
        for arr in (a, b, c):
            arr[moving] = rotate(arr[moving] - centre) + centre + shift
        n[moving] = rotate(n[moving])
        ctr[moving] = centre + shift
        return a, b, c, n, ctr

    def move_rigid(self, dt: float) -> None:
        """Move the rigid triangles by one step (their geometry at ``dt``)."""
        k = np.flatnonzero(self.moves)
        if len(k):
            self.a[k], self.b[k], self.c[k], self.normal[k], self.center[k] = self.geometry_at(k, dt)
            self._search = None

    def search_tree(self, dt: float) -> tuple:
        """Centroids (m, 3), bounding radii (m,) and the distance each triangle may move in a step
        of ``dt`` (m,), and a k-d tree of the centroids; kept until the rigid triangles move."""
        key = (float(dt), len(self))
        if self._search is None or self._search[0] != key:
            centroid = (self.a + self.b + self.c) / 3.0
            size = np.max([np.linalg.norm(v - centroid, axis=1) for v in (self.a, self.b, self.c)], axis=0)
            arm = np.max([np.linalg.norm(v - self.center, axis=1) for v in (self.a, self.b, self.c)], axis=0)
            travel = np.where(self.moves, np.linalg.norm(self.velocity, axis=1)
                              + np.linalg.norm(self.angular_velocity, axis=1) * arm, 0.0) * dt
            self._search = (key, centroid, size + travel, travel, cKDTree(centroid))
        return self._search[1:]

    def surface_velocity(self, k: np.ndarray, points: np.ndarray, centre: np.ndarray) -> np.ndarray:
        """(len(k), 3) wall velocity at ``points``: V + Ω × (p − centre); a surface-moving wall
        keeps its place, so its normal component is dropped."""
        u = self.velocity[k] + cross(self.angular_velocity[k], points - centre)
        surface = ~self.rigid[k]
        n = self.normal[k]
        u[surface] -= np.sum(u[surface] * n[surface], axis=1, keepdims=True) * n[surface]
        return u


def cross(a, b) -> np.ndarray:
    """a × b for 3-vectors or (k, 3) rows (np.cross is slow on small arrays)."""
    a, b = np.asarray(a), np.asarray(b)
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def rodrigues(axis_rate: np.ndarray, t: np.ndarray):
    """A function rotating (k, 3) vectors by the angles |Ω| t about Ω/|Ω| (one rotation per row)."""
    rate = np.linalg.norm(axis_rate, axis=1)
    angle = rate * t
    unit = np.divide(axis_rate, rate[:, None], out=np.zeros_like(axis_rate), where=rate[:, None] > 0)
    cos, sin = np.cos(angle)[:, None], np.sin(angle)[:, None]

    def rotate(vec):
        return (vec * cos + cross(unit, vec) * sin
                + unit * np.sum(unit * vec, axis=1, keepdims=True) * (1 - cos))
    return rotate


def build_walls(case, mesh) -> Walls:
    """Collective. The wall triangles of the case's mesh with their coefficients and motion.

    Wall boundaries: those of type "wall" and those not listed in the case (a fixed wall).
    Coefficients default to [collisions] (or 0.9 / 0.3 / 0.0 without it); [deposition] zones
    name the walls where particles stick.
    """
    names = [name for name in mesh.boundary_names
             if name not in case.boundaries or case.boundaries[name].type == "wall"]
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
        if section is not None:
            walls.velocity[rows] = section.velocity
            walls.angular_velocity[rows] = section.angular_velocity
            walls.center[rows] = section.center
            walls.rigid[rows] = section.motion == "rigid"
        walls.deposition[rows] = name in zones
    return walls


def collision_coefficients(case) -> dict:
    section = getattr(case, "collisions", None)
    if section is None:
        return {"restitution": DEFAULT_RESTITUTION, "friction": DEFAULT_FRICTION,
                "rolling_friction": DEFAULT_ROLLING_FRICTION}
    return {"restitution": section.restitution, "friction": section.friction,
            "rolling_friction": section.rolling_friction}


@dataclass(frozen=True)
class CollisionSettings:
    """Particle–particle coefficients and the event loop's limits.

    ``rest_speed`` (m/s): contacts approaching slower than this are inelastic (resting contact);
    ``max_events_per_particle``: the event budget of one step is this × the particle count (at
    least ``min_events``); past it the step ends with every remaining contact made inelastic.
    """

    restitution: float = DEFAULT_RESTITUTION
    friction: float = DEFAULT_FRICTION
    rolling_friction: float = DEFAULT_ROLLING_FRICTION
    rest_speed: float = 0.0
    max_events_per_particle: int = 50
    min_events: int = 1000
    max_sweeps: int = 500


def collision_settings(case) -> CollisionSettings:
    """Settings from [collisions] and [run]: rest speed 3 |g| dt (dt per particle substep)."""
    coefficients = collision_coefficients(case)
    substeps = case.coupling.substeps if getattr(case, "coupling", None) is not None else 1
    g = float(np.linalg.norm(case.run.gravity))
    rest = 3.0 * g * case.run.dt / substeps
    return CollisionSettings(**coefficients, rest_speed=rest if rest > 0 else 1e-9)


# ----------------------------------------------------------------------------------------------
# Geometry: closest points and contact times (vectorised over candidate pairs)
# ----------------------------------------------------------------------------------------------
def closest_points_on_triangles(p, a, b, c) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of each triangle (a, b, c) to each point p, all (k, 3).

    Returns the points (k, 3) and a (k,) bool, true where the closest point is inside the face
    (not on an edge or a vertex). Voronoi regions of the vertices, edges and face in turn.
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


def first_root(d, w, radius) -> np.ndarray:
    """First τ >= 0 with |d + w τ| = radius for points outside the sphere (|d| > radius) moving
    towards it; inf where none. d, w (k, 3) or (k, 2); radius (k,)."""
    A = np.sum(w * w, 1)
    B = np.sum(d * w, 1)
    C = np.sum(d * d, 1) - radius ** 2
    disc = B * B - A * C
    ok = (C > 0) & (B < 0) & (disc >= 0)
    tau = np.full(len(A), np.inf)
    tau[ok] = C[ok] / (-B[ok] + np.sqrt(disc[ok]))  # the smaller root, without cancellation
    return tau


def pair_contact_times(dx, dv, contact, horizon, quiet=0.0) -> np.ndarray:
    """Eq. 5-7: first τ in [0, horizon] with |dx + dv τ| = contact; 0 for touching pairs that
    approach faster than ``quiet`` (m/s); inf where none. dx = x_i − x_j, dv = v_i − v_j (k, 3),
    contact = r_i + r_j (k,)."""
    tau = first_root(dx, dv, contact)
    dist = np.linalg.norm(dx, axis=1)
    closing = -np.sum(dx * dv, 1) / np.maximum(dist, 1e-300)
    touching = dist <= contact * (1 + TOUCH_TOL)
    tau[touching] = np.where(closing[touching] > np.maximum(quiet, APPROACH_TOL * np.linalg.norm(dv[touching], axis=1)),
                             0.0, np.inf)
    tau[tau > horizon] = np.inf
    return tau


def wall_contact_times(p, w, radius, a, b, c, n, horizon, quiet=0.0) -> np.ndarray:
    """First τ in [0, horizon] at which a sphere (centre p + w τ, w relative to the triangle)
    touches triangle (a, b, c) from its domain side (normal n); 0 if it touches now and
    approaches; inf where none. All (k, 3) or (k,)."""
    k = len(radius)
    q, face = closest_points_on_triangles(p, a, b, c)
    height = np.sum((p - a) * n, 1)
    sep = p - q
    dist = np.linalg.norm(sep, axis=1)
    direction = np.where(face[:, None], n, sep / np.maximum(dist, 1e-300)[:, None])
    gap = np.where(face, height, dist) - radius
    behind = (height < -radius) | (~face & (height < 0))
    closing = -np.sum(w * direction, 1)
    touching = (gap <= TOUCH_TOL * radius) & ~behind
    tau = np.full(k, np.inf)
    tau[touching & (closing > np.maximum(quiet, APPROACH_TOL * np.linalg.norm(w, axis=1)))] = 0.0
    far = np.flatnonzero(~touching & ~behind)
    if len(far):
        tau[far] = swept_triangle_times(p[far], w[far], radius[far], a[far], b[far], c[far], n[far], height[far])
    tau[tau > horizon] = np.inf
    return tau


def swept_triangle_times(p, w, radius, a, b, c, n, height) -> np.ndarray:
    """First contact time of spheres not touching their triangle: the earliest valid contact of
    the face (plane distance r, foot inside), the three edges (distance r to the line, foot on the
    segment) and the three vertices. Contacts reached from behind the plane do not count."""
    wn = np.sum(w * n, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_face = np.where((wn < 0) & (height > radius), (height - radius) / -wn, np.inf)
    foot = p + w * np.where(np.isfinite(t_face), t_face, 0.0)[:, None] - n * radius[:, None]
    t_face[~inside_triangle(foot, a, b, c, n)] = np.inf
    times = [t_face]
    for start, end in ((a, b), (b, c), (c, a)):
        edge = end - start
        length = np.linalg.norm(edge, axis=1)
        unit = edge / length[:, None]
        d = p - start
        d_perp = d - np.sum(d * unit, 1)[:, None] * unit
        w_perp = w - np.sum(w * unit, 1)[:, None] * unit
        t = first_root(d_perp, w_perp, radius)
        fin = np.isfinite(t)
        along = np.sum((d + w * np.where(fin, t, 0.0)[:, None]) * unit, 1)
        t[fin & ((along < 0) | (along > length))] = np.inf
        times.append(t)
        times.append(first_root(d, w, radius))  # the edge's start vertex
    tau = np.min(times, axis=0)
    fin = np.isfinite(tau)
    front = np.sum((p + w * np.where(fin, tau, 0.0)[:, None] - a) * n, 1) >= -1e-12 * radius
    tau[~front] = np.inf
    return tau


def inside_triangle(x, a, b, c, n) -> np.ndarray:
    """(k,) bool: the in-plane point x lies in triangle (a, b, c) (edges included)."""
    tol = -1e-12
    return ((np.sum(cross(b - a, x - a) * n, 1) >= tol * np.sum(cross(b - a, c - a) * n, 1))
            & (np.sum(cross(c - b, x - b) * n, 1) >= tol * np.sum(cross(b - a, c - a) * n, 1))
            & (np.sum(cross(a - c, x - c) * n, 1) >= tol * np.sum(cross(b - a, c - a) * n, 1)))


def contact_impulse(u, n, inv_mass, k_t, e, mu) -> tuple[np.ndarray, bool]:
    """Impulse (3,) on body i at one contact: normal restitution e, Coulomb friction μ.

    u: relative contact velocity (i minus j), n: unit normal towards i, inv_mass: 1/m_i + 1/m_j,
    k_t: 1/m_i + r_i²/I_i + 1/m_j + r_j²/I_j. Returns the impulse and whether the contact sticks.
    """
    u_n = float(u @ n)
    j_n = -(1.0 + e) * u_n / inv_mass
    u_t = u - u_n * n
    stick = -u_t / k_t
    limit = mu * j_n
    size = float(np.sqrt(stick @ stick))
    if size <= limit:
        return j_n * n + stick, True
    return j_n * n + stick * (limit / size), False


# ----------------------------------------------------------------------------------------------
# The event loop
# ----------------------------------------------------------------------------------------------
def advance_with_collisions(state: ParticleState, walls: Walls | None, dt: float,
                            settings: CollisionSettings) -> dict:
    """Move every particle over ``dt`` with its contacts resolved in time order.

    Free particles move with constant velocity between contacts; fixed and deposited ones stay
    put, prescribed ones keep their velocity (all three have infinite mass); rigid walls move at
    the end of the step. Returns counts: particle_collisions, wall_collisions, events, capped.

    Rolling friction: at a resting, rolling contact with a wall (normal impulse J_n over the step)
    a torque μ_r N r opposes rolling; with the rolling constraint this slows the rolling velocity
    by (5/7) μ_r J_n / m (on a flat floor: deceleration (5/7) μ_r g) and the spin with it.
    """
    loop = EventLoop(state, walls, dt, settings)
    return loop.run()


class EventLoop:
    """One step's contacts (see ``advance_with_collisions``).

    Notes
    -----
    1. Resting contacts: the contacts touching at the start of the step that approach slower than
       ``rest_speed`` are solved together, inelastic with Coulomb friction, by Jacobi sweeps over
       the contact list with mass splitting (each body's mass shared among its contacts), until
       the velocity changes fall below 1e-4 ``rest_speed``. A stack or a bed thus settles in a few
       vectorised sweeps instead of thousands of tiny events.
    2. Impacts, in time order: each particle holds its position at its own last event time
       (``clock``); a counter per particle invalidates queued events once its velocity changes.
       Candidates come from a k-d tree of the step's initial positions, searched with a margin
       that bounds how far any particle can move in the step (the largest speed seen × dt).
       Touching contacts approaching slower than 1e-3 ``rest_speed`` are left to the next step's
       resting-contact solve.
    3. Past the event budget, the contacts left are solved as in 1 and everything flies freely to
       the end of the step.
    """

    def __init__(self, state, walls, dt, settings):
        self.state, self.walls, self.dt, self.settings = state, walls, float(dt), settings
        n = len(state)
        self.free = state.movable.copy()          # whose velocities respond to contacts
        stays = (state.motion == FIXED) | state.deposited
        self.v = np.where(stays[:, None], 0.0, state.v)
        self.x0 = state.x.copy()
        self.clock = np.zeros(n)
        self.count = np.zeros(n, np.int64)
        self.radius = state.radius
        self.inv_mass = np.zeros(n)
        self.inv_mass[self.free] = 1.0 / state.mass[self.free]
        self.inv_inertia = 2.5 * self.inv_mass / np.maximum(self.radius, 1e-300) ** 2  # 1/I, I = 2/5 m r²
        self.r_max = float(self.radius.max()) if n else 0.0
        self.speed = float(np.sqrt((self.v ** 2).sum(1).max())) if n else 0.0
        self.tree = cKDTree(self.x0) if n > 1 else None
        self.quiet = 1e-3 * settings.rest_speed
        self.heap, self.seq = [], 0
        self.stats = {"particle_collisions": 0, "wall_collisions": 0, "resting_contacts": 0, "events": 0,
                      "capped": False, "deposited": 0}
        self.max_events = max(settings.max_events_per_particle * n, settings.min_events)
        self.has_walls = walls is not None and len(walls) > 0 and bool(self.free.any())
        if self.has_walls:
            self.wall_centroid, self.wall_reach, self.wall_travel, self.wall_tree = walls.search_tree(self.dt)

    # -- the step ---------------------------------------------------------------------------------
    def run(self) -> dict:
        if len(self.state) == 0:
            return self.stats
        if self.settings.rest_speed > 0:
            self.settle()
        self.schedule_all()
        while self.heap:
            t, _, kind, i, j, cnt_i, cnt_j = heapq.heappop(self.heap)
            if cnt_i != self.count[i] or (kind == 0 and cnt_j != self.count[j]):
                continue
            if self.stats["events"] >= self.max_events:
                self.stats["capped"] = True
                self.advance_to(np.arange(len(self.state)), t)
                self.heap.clear()
                contacts = self.touching_contacts(t)
                self.solve_inelastic(contacts, bias_time=None)
                break
            self.stats["events"] += 1
            if kind == 0:
                self.particle_contact(t, i, j)
            else:
                self.wall_contact(t, i, j)
        self.finish()
        return self.stats

    def finish(self):
        """Every particle to the end of the step; velocities back into the state; walls move."""
        state = self.state
        self.advance_to(np.arange(len(state)), self.dt)
        free = state.motion == FREE  # deposited ones included: they now rest
        state.v[free] = self.v[free]
        if self.walls is not None and len(self.walls):
            self.walls.move_rigid(self.dt)

    # -- resting contacts, all at once ------------------------------------------------------------
    def touching_contacts(self, t) -> dict:
        """Every touching particle–particle and particle–wall contact at time t (all clocks at t).

        Returns arrays: i, j (j = n for a wall), normal (towards i), arm_i, arm_j (centre to contact
        point), u_wall, mu, mu_r, gap (m), wall (bool), k (triangle, −1 for pairs).
        """
        state, n = self.state, len(self.state)
        x, r = state.x, self.radius
        parts = []
        if n > 1:
            pairs = self.tree.query_pairs(2 * self.r_max * (1 + CONTACT_TOL) + 2 * self.speed * t,
                                          output_type="ndarray")
            i, j = pairs[:, 0], pairs[:, 1]
            dx = x[i] - x[j]
            dist = np.sqrt((dx * dx).sum(1))
            gap = dist - (r[i] + r[j])
            keep = (gap <= CONTACT_TOL * (r[i] + r[j])) & (self.free[i] | self.free[j]) & (dist > 0)
            i, j, dx, dist, gap = i[keep], j[keep], dx[keep], dist[keep], gap[keep]
            normal = dx / dist[:, None]
            m = len(i)
            parts.append(dict(i=i, j=j, normal=normal, arm_i=-r[i, None] * normal, arm_j=r[j, None] * normal,
                              u_wall=np.zeros((m, 3)), mu=np.full(m, self.settings.friction), mu_r=np.zeros(m),
                              gap=gap, wall=np.zeros(m, bool), k=np.full(m, -1)))
        if self.has_walls:
            p, k = self.wall_candidates(np.flatnonzero(self.free), r * CONTACT_TOL)
            if len(p):
                a, b, c, nf, ctr = self.walls.geometry_at(k, t)
                q, face = closest_points_on_triangles(x[p], a, b, c)
                sep = x[p] - q
                height = ((x[p] - a) * nf).sum(1)
                dist = np.sqrt((sep * sep).sum(1))
                gap = np.where(face, height, dist) - r[p]
                keep = (gap <= CONTACT_TOL * r[p]) & (height >= np.where(face, -r[p], 0.0)) & (face | (dist > 0))
                p, k, q, face, sep, dist, gap, nf, ctr = (arr[keep] for arr in (p, k, q, face, sep, dist, gap, nf, ctr))
                normal = np.where(face[:, None], nf, sep / np.maximum(dist, 1e-300)[:, None])
                m = len(p)
                parts.append(dict(i=p, j=np.full(m, n), normal=normal, arm_i=-r[p, None] * normal,
                                  arm_j=np.zeros((m, 3)), u_wall=self.walls.surface_velocity(k, q, ctr),
                                  mu=self.walls.friction[k], mu_r=self.walls.rolling_friction[k], gap=gap,
                                  wall=np.ones(m, bool), k=k))
        if not parts:
            return {}
        return {key: np.concatenate([part[key] for part in parts]) for key in parts[0]}

    def settle(self):
        """Solve the resting contacts of the step's start together (Notes, 1)."""
        contacts = self.touching_contacts(0.0)
        if not contacts or len(contacts["i"]) == 0:
            return
        i, j = contacts["i"], contacts["j"]
        n = len(self.state)
        u = self.relative_velocity(contacts)
        closing = -(u * contacts["normal"]).sum(1)
        slow = closing < self.settings.rest_speed
        contacts = {key: value[slow] for key, value in contacts.items()}
        # touching a deposition wall or a deposited particle: deposit
        i, j, k = contacts["i"], contacts["j"], contacts["k"]
        deposited = np.append(self.state.deposited, False)
        sticky = np.where(contacts["wall"], self.walls.deposition[k] if self.has_walls else False, deposited[j])
        for idx in np.unique(i[sticky & self.free[i]]):
            self.deposit(idx, 0.0, reschedule=False)
        if len(contacts["i"]):
            self.stats["resting_contacts"] += len(contacts["i"])
            self.solve_inelastic(contacts, bias_time=self.dt)

    def relative_velocity(self, c) -> np.ndarray:
        """(m, 3) contact-point velocity of body i relative to body j (row n: the wall)."""
        v = np.vstack([self.v, np.zeros((1, 3))])
        w = np.vstack([self.state.omega, np.zeros((1, 3))])
        i, j = c["i"], c["j"]
        return v[i] + cross(w[i], c["arm_i"]) - v[j] - cross(w[j], c["arm_j"]) - c["u_wall"]

    def solve_inelastic(self, c, bias_time):
        """Solve contacts ``c`` together: inelastic (e = 0), sticking unless the impulse leaves the
        Coulomb cone (then sliding with μ λ_n), separating ones dropped. Contacts that share no
        free particle with another are solved in closed form; the others by an active-set
        iteration on W Λ = target − u, W = J M⁻¹ Jᵀ (a sparse direct solve). Then rolling
        friction at the wall contacts that stick. With ``bias_time``, overlapping contacts
        separate at 0.2 overlap / bias_time, so round-off never accumulates into sinking."""
        c = unique_wall_contacts(c)
        m, n = len(c["i"]), len(self.state)
        if m == 0:
            return
        i, j, normal, mu = c["i"], c["j"], c["normal"], c["mu"]
        target = np.zeros(m) if bias_time is None else 0.2 * np.maximum(-c["gap"], 0.0) / bias_time
        u = self.relative_velocity(c)
        inv_m = np.append(self.inv_mass, 0.0)
        inv_i = np.append(self.inv_inertia, 0.0)
        free = inv_m > 0
        uses = np.bincount(i[free[i]], minlength=n + 1) + np.bincount(j[free[j]], minlength=n + 1)
        alone = (uses[i] <= 1) & (uses[j] <= 1)
        impulse, sticking = np.zeros((m, 3)), np.zeros(m, bool)
        if alone.any():
            w_n = inv_m[i[alone]] + inv_m[j[alone]]
            k_t = (w_n + inv_i[i[alone]] * (c["arm_i"][alone] ** 2).sum(1)
                   + inv_i[j[alone]] * (c["arm_j"][alone] ** 2).sum(1))
            impulse[alone], sticking[alone] = isolated_impulses(u[alone], normal[alone], w_n, k_t, target[alone],
                                                                mu[alone])
        group = np.flatnonzero(~alone)
        if len(group):
            sub = {key: value[group] for key, value in c.items()}
            impulse[group], sticking[group] = self.coupled_impulses(sub, u[group], target[group])
        self.v += bincount3(i, impulse * inv_m[i, None], n + 1)[:n] - bincount3(j, impulse * inv_m[j, None], n + 1)[:n]
        self.state.omega += (bincount3(i, cross(c["arm_i"], impulse) * inv_i[i, None], n + 1)[:n]
                             - bincount3(j, cross(c["arm_j"], impulse) * inv_i[j, None], n + 1)[:n])
        lam_n = (impulse * normal).sum(1)
        rolling = c["wall"] & (c["mu_r"] > 0) & (lam_n > 0) & sticking
        for idx in np.flatnonzero(rolling):  # the wall contacts of rolling particles
            self.roll_resistance(i[idx], normal[idx], c["u_wall"][idx], lam_n[idx], c["mu_r"][idx])
        touched = np.concatenate([i, j[j < n]])
        self.speed = max(self.speed, float(np.sqrt((self.v[touched] ** 2).sum(1).max())))

    def coupled_impulses(self, c, u, target):
        """(m, 3) impulses and (m,) sticking flags of contacts that share particles."""
        m, n = len(c["i"]), len(self.state)
        normal, mu = c["normal"], c["mu"]
        jac = contact_jacobian(c, self.inv_mass > 0, n)
        inv_m6 = np.repeat(np.column_stack([self.inv_mass, self.inv_inertia]), 3, axis=1).ravel()
        W = (jac @ sparse.diags(inv_m6) @ jac.T).tocsr()
        status = np.zeros(m, np.int8)  # 0 sticking, 1 sliding, 2 separating
        direction = np.zeros((m, 3))   # friction direction of the sliding ones
        impulse = np.zeros((m, 3))
        for _ in range(20):
            impulse = solve_active_set(W, u, normal, target, mu, status, direction)
            lam_n = (impulse * normal).sum(1)
            tang = impulse - lam_n[:, None] * normal
            size = np.sqrt((tang * tang).sum(1))
            after = u + (W @ impulse.ravel()).reshape(m, 3)
            approaching = (after * normal).sum(1) < target - 1e-9 * (np.abs(u).max() + target.max())
            new = status.copy()
            new[(status < 2) & (lam_n < 0)] = 2
            slide = (status == 0) & (lam_n >= 0) & (size > mu * lam_n * (1 + 1e-9))
            new[slide] = 1
            direction[slide] = tang[slide] / size[slide, None]
            new[(status == 2) & approaching] = 0
            if np.array_equal(new, status):
                break
            status = new
        return impulse, status == 0

    # -- impacts, in time order -------------------------------------------------------------------
    def push(self, times, kind, i, others, start):
        """Queue the finite contact times (relative to ``start``) of particle(s) i with others."""
        fin = np.isfinite(times)
        if not fin.any():
            return
        i = np.broadcast_to(i, times.shape)[fin]
        others, times = others[fin], times[fin] + start
        cnt_i = self.count[i]
        cnt_j = self.count[others] if kind == 0 else np.full(len(others), -1)
        for entry in zip(times.tolist(), i.tolist(), others.tolist(), cnt_i.tolist(), cnt_j.tolist()):
            self.seq += 1
            heapq.heappush(self.heap, (entry[0], self.seq, kind, *entry[1:]))

    def position(self, idx, t):
        return self.state.x[idx] + self.v[idx] * np.reshape(t - self.clock[idx], np.shape(idx) + (1,))

    def advance_to(self, idx, t):
        self.state.x[idx] = self.position(idx, t)
        self.clock[idx] = t

    def schedule_all(self):
        """The first contacts of every particle, vectorised over candidate pairs."""
        if self.tree is not None:
            pairs = self.tree.query_pairs(2 * self.r_max + 2 * self.speed * self.dt, output_type="ndarray")
            i, j = pairs[:, 0], pairs[:, 1]
            keep = self.free[i] | self.free[j]
            i, j = i[keep], j[keep]
            dx, dv = self.state.x[i] - self.state.x[j], self.v[i] - self.v[j]
            contact = self.radius[i] + self.radius[j]
            near = np.sqrt((dx * dx).sum(1)) <= contact + np.sqrt((dv * dv).sum(1)) * self.dt
            times = pair_contact_times(dx[near], dv[near], contact[near], self.dt, self.quiet)
            self.push(times, 0, i[near], j[near], 0.0)
        if self.has_walls:
            self.push_wall_events(np.flatnonzero(self.free), 0.0)

    def schedule(self, i, t):
        """Recompute particle i's contacts from time t (its velocity just changed at t)."""
        horizon = self.dt - t
        if horizon <= 0:
            return
        if self.tree is not None:
            x_i = self.state.x[i]
            reach = self.radius[i] + self.r_max + self.speed * self.dt + np.sqrt(self.v[i] @ self.v[i]) * horizon
            nb = np.asarray(self.tree.query_ball_point(x_i, reach), dtype=np.int64)
            nb = nb[(nb != i) & (self.free[i] | self.free[nb])]
            if len(nb):
                times = pair_contact_times(x_i - self.position(nb, t), self.v[i] - self.v[nb],
                                           self.radius[i] + self.radius[nb], horizon, self.quiet)
                self.push(times, 0, i, nb, t)
        if self.has_walls and self.free[i]:
            self.push_wall_events(np.array([i]), t)

    def wall_candidates(self, particles, travel):
        """(particle, triangle) index pairs that may touch after moving ``travel`` (per particle):
        bounding spheres that meet, and a plane within reach on the domain side."""
        none = np.zeros(0, np.int64)
        if len(particles) == 0:
            return none, none
        x = self.state.x[particles]
        reach = self.radius[particles] + np.broadcast_to(travel, len(self.radius))[particles]
        found = self.wall_tree.query_ball_point(x, reach + self.wall_reach.max())
        sizes = np.fromiter((len(f) for f in found), np.int64, len(found))
        if sizes.sum() == 0:
            return none, none
        row = np.repeat(np.arange(len(particles)), sizes)
        k = np.fromiter((t for f in found for t in f), np.int64, int(sizes.sum()))
        d = x[row] - self.wall_centroid[k]
        height = (d * self.walls.normal[k]).sum(1)  # the centroid lies in the plane
        near = ((np.sqrt((d * d).sum(1)) <= reach[row] + self.wall_reach[k])
                & (height <= reach[row] + self.wall_travel[k])
                & (height >= -self.radius[particles[row]] - self.wall_travel[k]))
        return particles[row[near]], k[near]

    def push_wall_events(self, particles, t):
        """Queue the wall contacts of ``particles`` (all at their clock = t) from time t."""
        horizon = self.dt - t
        speed = np.sqrt((self.v * self.v).sum(1))
        i, k = self.wall_candidates(particles, speed * horizon)
        if len(i) == 0:
            return
        a, b, c, n, ctr = self.walls.geometry_at(k, t)
        p = self.state.x[i]
        moves = self.walls.moving(k)
        u_wall = np.zeros((len(k), 3))
        if moves.any():
            q, _ = closest_points_on_triangles(p[moves], a[moves], b[moves], c[moves])
            u_wall[moves] = self.walls.surface_velocity(k[moves], q, ctr[moves])
        times = wall_contact_times(p, self.v[i] - u_wall, self.radius[i], a, b, c, n, horizon, self.quiet)
        self.push(times, 1, i, k, t)

    def changed(self, idx, t):
        """Particle idx has a new velocity at t: invalidate and recompute its contacts."""
        self.count[idx] += 1
        self.speed = max(self.speed, float(np.sqrt(self.v[idx] @ self.v[idx])))
        self.schedule(idx, t)

    def deposit(self, i, t, reschedule=True):
        self.v[i] = 0.0
        self.state.omega[i] = 0.0
        self.state.deposited[i] = True
        self.free[i] = False
        self.inv_mass[i] = self.inv_inertia[i] = 0.0
        self.stats["deposited"] += 1
        if reschedule:
            self.changed(i, t)

    def particle_contact(self, t, i, j):
        state = self.state
        self.advance_to(np.array([i, j]), t)
        dx = state.x[i] - state.x[j]
        n = dx / np.sqrt(dx @ dx)
        arm_i, arm_j = -self.radius[i] * n, self.radius[j] * n
        u = (self.v[i] + cross(state.omega[i], arm_i)) - (self.v[j] + cross(state.omega[j], arm_j))
        closing = -float(u @ n)
        if closing <= APPROACH_TOL * np.sqrt(u @ u):
            return
        self.stats["particle_collisions"] += 1
        if state.deposited[j] and self.free[i]:
            return self.deposit(i, t)
        if state.deposited[i] and self.free[j]:
            return self.deposit(j, t)
        s = self.settings
        e = s.restitution if closing >= s.rest_speed else 0.0
        inv_mass = self.inv_mass[i] + self.inv_mass[j]
        k_t = inv_mass + self.inv_inertia[i] * self.radius[i] ** 2 + self.inv_inertia[j] * self.radius[j] ** 2
        J, _ = contact_impulse(u, n, inv_mass, k_t, e, s.friction)
        for idx, arm, sign in ((i, arm_i, 1.0), (j, arm_j, -1.0)):
            if self.free[idx]:
                self.v[idx] += sign * self.inv_mass[idx] * J
                state.omega[idx] += sign * self.inv_inertia[idx] * cross(arm, J)
        for idx in (i, j):
            if self.free[idx]:
                self.changed(idx, t)

    def wall_contact(self, t, i, k):
        state, walls = self.state, self.walls
        self.advance_to(np.array([i]), t)
        ks = np.array([k])
        a, b, c, n_face, ctr = walls.geometry_at(ks, t)
        x = state.x[i:i + 1]
        q, face = closest_points_on_triangles(x, a, b, c)
        sep = (x - q)[0]
        dist = float(np.sqrt(sep @ sep))
        n = n_face[0] if face[0] else sep / dist
        gap = (float(sep @ n_face[0]) if face[0] else dist) - self.radius[i]
        if gap > GAP_TOL * self.radius[i]:  # a rotating wall's linearised path missed: look again
            self.count[i] += 1
            self.schedule(i, t)
            return
        arm = -self.radius[i] * n
        u_wall = walls.surface_velocity(ks, x + arm, ctr)[0]
        u = self.v[i] + cross(state.omega[i], arm) - u_wall
        closing = -float(u @ n)
        if closing <= APPROACH_TOL * np.sqrt(u @ u):
            return
        self.stats["wall_collisions"] += 1
        if walls.deposition[k]:
            return self.deposit(i, t)
        resting = closing < self.settings.rest_speed
        e = 0.0 if resting else walls.restitution[k]
        inv_mass = self.inv_mass[i]
        J, sticking = contact_impulse(u, n, inv_mass, 3.5 * inv_mass, e, walls.friction[k])
        self.v[i] += inv_mass * J
        state.omega[i] += self.inv_inertia[i] * cross(arm, J)
        if resting and sticking and walls.rolling_friction[k] > 0:
            self.roll_resistance(i, n, u_wall, float(J @ n), walls.rolling_friction[k])
        self.changed(i, t)

    def roll_resistance(self, i, n, u_wall, j_n, mu_r):
        """Slow a rolling particle by (5/7) μ_r J_n / m, keeping it rolling (no reversal)."""
        rolling = self.v[i] - u_wall
        rolling = rolling - (rolling @ n) * n
        speed = float(np.sqrt(rolling @ rolling))
        if speed == 0.0:
            return
        dv = -min(5.0 / 7.0 * mu_r * j_n * self.inv_mass[i], speed) * rolling / speed
        self.v[i] += dv
        self.state.omega[i] += cross(n, dv) / self.radius[i]


def isolated_impulses(u, normal, w_n, k_t, target, mu) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form inelastic impulses (m, 3) of independent contacts: normal velocity brought to
    ``target`` (never pulling), tangential velocity stopped within the Coulomb cone; and the
    (m,) sticking flags."""
    u_n = (u * normal).sum(1)
    lam_n = np.maximum((target - u_n) / w_n, 0.0)
    stick = -(u - u_n[:, None] * normal) / k_t[:, None]
    size = np.sqrt((stick * stick).sum(1))
    limit = mu * lam_n
    sticking = size <= limit
    scale = np.where(sticking, 1.0, limit / np.maximum(size, 1e-300))
    return lam_n[:, None] * normal + stick * scale[:, None], sticking


def unique_wall_contacts(c) -> dict:
    """Drop repeated wall contacts of one particle with the same normal (a sphere over the shared
    edge of two coplanar triangles touches both at one point)."""
    if not c or not c["wall"].any():
        return c
    key = np.column_stack([c["i"], np.round(c["normal"] * 1e6), ~c["wall"] * np.arange(len(c["i"]))])
    _, first = np.unique(key, axis=0, return_index=True)
    keep = np.sort(first)
    return {name: value[keep] for name, value in c.items()}


def contact_jacobian(c, free, n) -> sparse.csr_matrix:
    """(3m, 6n) sparse map from body velocities (v, ω per body) to relative contact velocities:
    u_c = Σ_b s_cb (v_b − [a_cb]× ω_b), s = +1 for body i, −1 for body j; fixed bodies left out."""
    m = len(c["i"])
    rows, cols, vals = [], [], []
    for body, arm, sign in ((c["i"], c["arm_i"], 1.0), (c["j"], c["arm_j"], -1.0)):
        use = np.flatnonzero(body < n)
        use = use[free[body[use]]]
        if len(use) == 0:
            continue
        b, a = body[use], arm[use]
        zero = np.zeros(len(use))
        # block [I | -[a]x], row-major 3 x 6
        block = np.stack([
            np.stack([np.ones_like(zero), zero, zero, zero, a[:, 2], -a[:, 1]], 1),
            np.stack([zero, np.ones_like(zero), zero, -a[:, 2], zero, a[:, 0]], 1),
            np.stack([zero, zero, np.ones_like(zero), a[:, 1], -a[:, 0], zero], 1)], 1) * sign
        r = 3 * use[:, None, None] + np.arange(3)[None, :, None]
        q = 6 * b[:, None, None] + np.arange(6)[None, None, :]
        rows.append(np.broadcast_to(r, block.shape).ravel())
        cols.append(np.broadcast_to(q, block.shape).ravel())
        vals.append(block.ravel())
    if not rows:
        return sparse.csr_matrix((3 * m, 6 * n))
    return sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(3 * m, 6 * n))


def solve_active_set(W, u, normal, target, mu, status, direction) -> np.ndarray:
    """(m, 3) contact impulses for one guess of the contact states: sticking contacts (0) end with
    relative velocity target·n, sliding ones (1) with normal velocity target and impulse
    λ_n (n + μ f), separating ones (2) carry none."""
    m = len(status)
    stick, slide = np.flatnonzero(status == 0), np.flatnonzero(status == 1)
    n_unknowns = 3 * len(stick) + len(slide)
    if n_unknowns == 0:
        return np.zeros((m, 3))
    # P: unknowns → impulses (3m); E: equations picked from the 3m velocity rows
    cols_stick = np.arange(3 * len(stick))
    rows_stick = (3 * stick[:, None] + np.arange(3)).ravel()
    d = normal[slide] + mu[slide, None] * direction[slide]
    col_slide = 3 * len(stick) + np.arange(len(slide))
    P = sparse.csr_matrix((np.concatenate([np.ones(len(rows_stick)), d.ravel()]),
                           (np.concatenate([rows_stick, (3 * slide[:, None] + np.arange(3)).ravel()]),
                            np.concatenate([cols_stick, np.repeat(col_slide, 3)]))), shape=(3 * m, n_unknowns))
    E = sparse.csr_matrix((np.concatenate([np.ones(len(rows_stick)), normal[slide].ravel()]),
                           (np.concatenate([cols_stick, np.repeat(col_slide, 3)]),
                            np.concatenate([rows_stick, (3 * slide[:, None] + np.arange(3)).ravel()]))),
                          shape=(n_unknowns, 3 * m))
    A = (E @ W @ P).tocsc()
    rhs = E @ (target[:, None] * normal - u).ravel()
    scale = np.abs(A.diagonal()).max()
    A = A + sparse.identity(n_unknowns, format="csc") * (1e-10 * scale)  # redundant contacts share
    z = spsolve(A, rhs) if n_unknowns > 1 else rhs / A.toarray()[0]
    return (P @ np.atleast_1d(z)).reshape(m, 3)


def bincount3(index, values, n) -> np.ndarray:
    """(n, 3) sums of the (k, 3) ``values`` by row ``index``."""
    return np.column_stack([np.bincount(index, values[:, d], minlength=n) for d in range(3)])


# ----------------------------------------------------------------------------------------------
# Checks of new particles
# ----------------------------------------------------------------------------------------------
def check_initial_particles(case, new, inside, walls: Walls | None) -> None:
    """Refuse initial particles outside the domain, overlapping each other or a wall (CaseError)."""
    name = case.path.name
    outside = np.flatnonzero(~np.asarray(inside, bool))
    if len(outside):
        i = outside[0]
        raise CaseError(f"{name}: particle {i}: centre {fmt(new.x[i])} is outside the domain")
    n = len(new)
    if n > 1:
        tree = cKDTree(new.x)
        pairs = tree.query_pairs(2 * float(new.radius.max()), output_type="ndarray")
        dist = np.linalg.norm(new.x[pairs[:, 0]] - new.x[pairs[:, 1]], axis=1)
        bad = dist < (new.radius[pairs[:, 0]] + new.radius[pairs[:, 1]]) * (1 - 1e-9)
        if bad.any():
            i, j = pairs[bad][np.argmin(pairs[bad].max(1))]
            i, j = sorted((int(i), int(j)))
            raise CaseError(f"{name}: particle {j} (centre {fmt(new.x[j])}, radius {new.radius[j]:g}) "
                            f"overlaps particle {i} (centre {fmt(new.x[i])}, radius {new.radius[i]:g})")
    if walls is not None and len(walls) and n:
        distance = wall_distances(new.x, walls, new.radius)
        bad = np.flatnonzero(distance < new.radius * (1 - 1e-9))
        if len(bad):
            i = bad[0]
            raise CaseError(f"{name}: particle {i}: centre {fmt(new.x[i])} is {distance[i]:.6g} m from a wall, "
                            f"less than its radius {new.radius[i]:g} m")


def wall_distances(x, walls: Walls, reach) -> np.ndarray:
    """(n,) distance from each point to the nearest wall triangle within ``reach`` (inf beyond)."""
    centroid = (walls.a + walls.b + walls.c) / 3.0
    size = np.max([np.linalg.norm(v - centroid, axis=1) for v in (walls.a, walls.b, walls.c)], axis=0)
    found = cKDTree(centroid).query_ball_point(x, np.broadcast_to(reach, len(x)) + size.max())
    sizes = np.fromiter((len(f) for f in found), np.int64, len(found))
    out = np.full(len(x), np.inf)
    if sizes.sum():
        p = np.repeat(np.arange(len(x)), sizes)
        k = np.concatenate([np.asarray(f, np.int64) for f in found])
        q, _ = closest_points_on_triangles(x[p], walls.a[k], walls.b[k], walls.c[k])
        np.minimum.at(out, p, np.linalg.norm(x[p] - q, axis=1))
    return out


def overlaps_existing(state: ParticleState, new) -> np.ndarray:
    """(len(new),) bool: new particles that overlap a particle of ``state`` or an earlier new one."""
    m = len(new)
    bad = np.zeros(m, bool)
    if m == 0:
        return bad
    if len(state):
        r_max = float(state.radius.max()) + float(new.radius.max())
        found = cKDTree(state.x).query_ball_point(new.x, r_max)
        for i, nb in enumerate(found):  # loops over the few new particles of one release
            nb = np.asarray(nb, np.int64)
            if len(nb):
                d = np.linalg.norm(state.x[nb] - new.x[i], axis=1)
                bad[i] = np.any(d < (state.radius[nb] + new.radius[i]) * (1 - 1e-9))
    if m > 1:
        pairs = cKDTree(new.x).query_pairs(2 * float(new.radius.max()), output_type="ndarray")
        pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))] if len(pairs) else pairs
        for i, j in pairs:  # later one loses, unless the earlier was already dropped
            i, j = min(i, j), max(i, j)
            if not bad[i] and not bad[j]:
                if np.linalg.norm(new.x[i] - new.x[j]) < (new.radius[i] + new.radius[j]) * (1 - 1e-9):
                    bad[j] = True
    return bad


def fmt(vector) -> str:
    return "(" + ", ".join(f"{float(v):.6g}" for v in vector) + ")"
