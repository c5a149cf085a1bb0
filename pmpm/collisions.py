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
slower than ``rest_speed`` (of the order of |g| dt) is a resting contact: inelastic (e = 0), and
solved together with the resting contacts around it (a stack, a bed) by a small linear
complementarity solve instead of a cascade of ever smaller, ever more frequent bounces.

Dense packings (a hopper: thousands of contacts per step) are not stepped event by event: a step
that starts with many contacts solves them all at once (time-stepping contact dynamics,
``EventLoop.dense_step``), at a cost that grows with the contacts, not with the events.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass, field, replace
from itertools import chain

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from .contact_kernels import closing_pairs, projected_gauss_seidel
from .errors import CaseError
from .particles import FIXED, FREE, ParticleState

DEFAULT_RESTITUTION, DEFAULT_FRICTION, DEFAULT_ROLLING_FRICTION = 0.9, 0.3, 0.0
APPROACH_TOL = 1e-9   # relative: approach speeds below 1e-9 |u| are round-off, not contacts
TOUCH_TOL = 1e-9      # relative: spheres this close count as touching
CONTACT_TOL = 1e-6    # relative: resting contacts are those this close at the start of a step
LOCAL_REACH = 6       # a slow contact mid-step settles the particles within this many radii
GS_SWEEPS = 50        # Gauss–Seidel sweeps for the friction of coupled resting contacts
DENSE_ROWS = 600      # contact systems up to this size are solved with dense matrices
PARALLEL = 1 - 1e-4   # wall contacts of one particle with normals closer than ~0.8° count as one
COLD_SWEEPS = 20      # × dense_sweeps for a dense step without a warm start
DENSE_TOL = 1e-2      # relative to rest_speed: a dense step's sweeps stop when no velocity changes more
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

    def moved(self, dt: float) -> "Walls":
        """These walls a step of ``dt`` later: the rigid triangles moved (a new object; this one stays)."""
        k = np.flatnonzero(self.moves)
        if len(k) == 0:
            return self
        a, b, c, normal, center = self.a.copy(), self.b.copy(), self.c.copy(), self.normal.copy(), self.center.copy()
        a[k], b[k], c[k], normal[k], center[k] = self.geometry_at(k, dt)
        return replace(self, a=a, b=b, c=c, normal=normal, center=center)

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
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), np.result_type(a, b))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


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

    The boundaries particles meet as walls (``particles_bounce``): walls (listed or not), inlets (a
    distributor plate) and symmetry planes, unless ``particles = "pass"``; outlets only with
    ``particles = "wall"``. Coefficients default to [collisions] (or 0.9 / 0.3 / 0.0 without it);
    [deposition] zones name the walls where particles stick. Only a wall's own motion moves it
    (an inlet's velocity is the fluid's).
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
    return walls


def particles_bounce(section) -> bool:
    """Whether particles meet a boundary (its case section, None: an unlisted wall) as a wall."""
    if section is None:
        return True
    choice = getattr(section, "particles", None)
    if choice is not None:
        return choice == "wall"
    return section.type != "outlet"


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
    ``dense_contacts``: a step that starts with at least this many contacts (touching, or able to
    close within the step) is a dense step, solved at once (``EventLoop.dense_step``) instead of
    event by event; 0 never. ``dense_sweeps``: the most Gauss–Seidel sweeps of a dense step.
    """

    restitution: float = DEFAULT_RESTITUTION
    friction: float = DEFAULT_FRICTION
    rolling_friction: float = DEFAULT_ROLLING_FRICTION
    rest_speed: float = 0.0
    max_events_per_particle: int = 50
    min_events: int = 1000
    dense_contacts: int = 256
    dense_sweeps: int = 20


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
    # the distance to a triangle is at least the height over its plane: a sphere that stays
    # above (height - r not reached at the normal speed) never touches it
    wn = np.sum(w * n, 1)
    out_of_reach = height - radius > np.maximum(-wn, 0.0) * horizon
    far = np.flatnonzero(~touching & ~behind & ~out_of_reach)
    if len(far):
        tau[far] = swept_triangle_times(p[far], w[far], radius[far], a[far], b[far], c[far], n[far], height[far])
    tau[tau > horizon] = np.inf
    return tau


def swept_triangle_times(p, w, radius, a, b, c, n, height) -> np.ndarray:
    """First contact time of spheres not touching their triangle: the earliest valid contact of
    the face (plane distance r, foot inside), the three edges (distance r to the line, foot on the
    segment) and the three vertices. Contacts reached from behind the plane do not count."""
    wn = np.sum(w * n, 1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
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
@dataclass(frozen=True)
class ContactMemory:
    """What the contact solver carries from one step to the next: the impulses of the last dense
    step (a warm start for the next), by contact key (particle ids, or id and wall triangle), sorted."""

    keys: np.ndarray          # (m,) int64
    normal: np.ndarray        # (m,) normal impulse on the key's first particle (N s)
    tangential: np.ndarray    # (m, 3) tangential impulse on it (N s)
    sign: np.ndarray          # (m,) +1, or −1 where the contact's i is the key's second particle

    def to_arrays(self) -> dict:
        return {"keys": self.keys, "normal": self.normal, "tangential": self.tangential, "sign": self.sign}

    @classmethod
    def from_arrays(cls, arrays: dict) -> "ContactMemory":
        return cls(np.asarray(arrays["keys"], np.int64), np.asarray(arrays["normal"], float),
                   np.asarray(arrays["tangential"], float).reshape(-1, 3), np.asarray(arrays["sign"], float))


@dataclass(frozen=True)
class ContactStep:
    """What a step of contacts returns: its counts, the solver's memory for the next step, and the
    walls at the end of the step (rigid ones moved)."""

    stats: dict
    memory: ContactMemory | None
    walls: Walls | None


def advance_with_collisions(state: ParticleState, walls: Walls | None, dt: float,
                            settings: CollisionSettings, memory: ContactMemory | None = None) -> ContactStep:
    """Move every particle over ``dt`` with its contacts resolved in time order (``state`` in place).

    Free particles move with constant velocity between contacts; fixed and deposited ones stay
    put, prescribed ones keep their velocity (all three have infinite mass); rigid walls move at
    the end of the step (see ``EventLoop`` for the algorithm). ``memory``: the last step's
    (``ContactStep.memory``). Counts of the step, in ``ContactStep.stats``:
    particle_collisions, wall_collisions, resting_contacts (solved at its start), events,
    deposited, fallbacks (ill-posed contact sets solved by sweeps) and capped (bool: the event
    budget ran out and the step ended with every contact left made inelastic).

    Rolling friction: at a resting, rolling contact with a wall (normal impulse J_n over the step)
    a torque μ_r N r opposes rolling; with the rolling constraint this slows the rolling velocity
    by (5/7) μ_r J_n / m (on a flat floor: deceleration (5/7) μ_r g) and the spin with it.
    """
    loop = EventLoop(state, walls, dt, settings, memory)
    stats = loop.run()
    return ContactStep(stats, loop.memory, walls.moved(dt) if walls is not None else None)


class EventLoop:
    """One step's contacts (see ``advance_with_collisions``).

    Notes
    -----
    1. Resting contacts, at the start of the step: every contact touching (gap <= 1e-6 r), or
       closing a face or pair gap that shuts within the step, and approaching slower than
       ``rest_speed``, is solved at once (``solve_inelastic``): e = 0, Coulomb friction, never
       pulling; a contact with a gap may close it, an overlap opens at 0.2 overlap / dt.
    2. Impacts, in time order: each particle holds its position at its own last event time
       (``clock``); a counter per particle invalidates queued events once its velocity changes.
       Candidates come from a k-d tree of the step's initial positions, searched with a margin
       that bounds how far any particle can move in the step (the largest speed seen × dt). A
       slow impact mid-step settles the resting contacts around it as in 1
       (``settle_locally``). Touching contacts approaching slower than 1e-3 ``rest_speed`` are
       left to the next step.
    3. Past the event budget, every touching contact is solved as in 1 and everything flies
       freely to the end of the step (``capped`` in the returned counts).
    4. A dense step (a bed, a hopper: at least ``dense_contacts`` contacts touching or able to
       close within the step) skips 1-3: all its contacts are solved at once (``dense_step``),
       impacts with their restitution, resting ones inelastic; events would cascade there.
    """

    def __init__(self, state, walls, dt, settings, memory=None):
        self.state, self.walls, self.dt, self.settings = state, walls, float(dt), settings
        self.remembered, self.memory = memory, None   # the last step's memory, and this step's
        self.end = self.dt * (1 - 1e-9)
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
                      "capped": False, "deposited": 0, "fallbacks": 0, "dense_steps": 0, "dense_contacts": 0, "sweeps": 0}
        self.max_events = max(settings.max_events_per_particle * n, settings.min_events)
        self.has_walls = walls is not None and len(walls) > 0 and bool(self.free.any())
        if self.has_walls:
            self.wall_centroid, self.wall_reach, self.wall_travel, self.wall_tree = walls.search_tree(self.dt)

    # -- the step ---------------------------------------------------------------------------------
    def run(self) -> dict:
        if len(self.state) == 0:
            return self.stats
        if self.settings.dense_contacts > 0 and 2 * len(self.state) >= self.settings.dense_contacts:
            contacts = self.step_contacts()
            if contacts and len(contacts["i"]) >= self.settings.dense_contacts:
                self.dense_step(contacts)
                self.finish()
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
                self.solve_inelastic(self.touching_contacts(t), self.dt - t)
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

    # -- resting contacts, all at once ------------------------------------------------------------
    def touching_contacts(self, t, reach=0.0, members=None, closing_in=None) -> dict:
        """Particle–particle and particle–wall contacts at time t whose gap is at most ``reach``
        (m) beyond touching, among ``members`` (default: all particles; their clocks at t); with
        ``closing_in`` (s), only those whose gap can close within it at the relative speed of
        the centres (a wall: of the centre and the wall).

        Returns arrays: i, j (j = n for a wall), normal (towards i), arm_i, arm_j (centre to contact
        point), u_wall, mu, mu_r, gap (m), wall (bool), face (bool: a wall contact inside the
        triangle's face), k (triangle, −1 for pairs).
        """
        state, n = self.state, len(self.state)
        x, r = state.x, self.radius
        parts = []
        span = 2 * self.r_max * (1 + CONTACT_TOL) + reach
        if members is None:
            members = np.arange(n)
            pairs = (self.tree.query_pairs(span + 2 * self.speed * t, output_type="ndarray") if n > 1
                     else np.zeros((0, 2), np.int64))
        else:
            pairs = members[cKDTree(x[members]).query_pairs(span, output_type="ndarray")] if len(members) > 1 \
                else np.zeros((0, 2), np.int64)
        if len(pairs):
            if closing_in is not None:  # many candidates, few kept: filter them compiled
                pairs = pairs[closing_pairs(pairs, x, self.v, r, self.free, reach, closing_in, CONTACT_TOL)]
            i, j = pairs[:, 0], pairs[:, 1]
            dx = x[i] - x[j]
            dist = np.sqrt((dx * dx).sum(1))
            gap = dist - (r[i] + r[j])
            keep = (gap <= CONTACT_TOL * (r[i] + r[j]) + reach) & (self.free[i] | self.free[j]) & (dist > 0)
            i, j, dx, dist, gap = i[keep], j[keep], dx[keep], dist[keep], gap[keep]
            normal = dx / dist[:, None]
            m = len(i)
            parts.append(dict(i=i, j=j, normal=normal, arm_i=-r[i, None] * normal, arm_j=r[j, None] * normal,
                              u_wall=np.zeros((m, 3)), mu=np.full(m, self.settings.friction), mu_r=np.zeros(m),
                              gap=gap, wall=np.zeros(m, bool), face=np.zeros(m, bool), k=np.full(m, -1)))
        if self.has_walls:
            mobile = members[self.free[members]]
            p, k = self.wall_candidates(mobile, r[mobile] * CONTACT_TOL + reach)
            if len(p):
                a, b, c, nf, ctr = self.walls.geometry_at(k, t)
                q, face = closest_points_on_triangles(x[p], a, b, c)
                sep = x[p] - q
                height = ((x[p] - a) * nf).sum(1)
                dist = np.sqrt((sep * sep).sum(1))
                gap = np.where(face, height, dist) - r[p]
                keep = ((gap <= CONTACT_TOL * r[p] + reach) & (height >= np.where(face, -r[p], 0.0))
                        & (face | (dist > 0)))
                p, k, q, face, sep, dist, gap, nf, ctr = (arr[keep] for arr in (p, k, q, face, sep, dist, gap, nf, ctr))
                u_wall = self.walls.surface_velocity(k, q, ctr)
                if closing_in is not None:
                    dv = self.v[p] - u_wall
                    keep = gap <= np.sqrt((dv * dv).sum(1)) * closing_in + CONTACT_TOL * r[p]
                    p, k, face, sep, dist, gap, nf, u_wall = (arr[keep]
                                                              for arr in (p, k, face, sep, dist, gap, nf, u_wall))
                normal = np.where(face[:, None], nf, sep / np.maximum(dist, 1e-300)[:, None])
                m = len(p)
                parts.append(dict(i=p, j=np.full(m, n), normal=normal, arm_i=-r[p, None] * normal,
                                  arm_j=np.zeros((m, 3)), u_wall=u_wall,
                                  mu=self.walls.friction[k], mu_r=self.walls.rolling_friction[k], gap=gap,
                                  wall=np.ones(m, bool), face=face, k=k))
        if not parts:
            return {}
        return {key: np.concatenate([part[key] for part in parts]) for key in parts[0]}

    def settle(self):
        """Solve together the slow contacts of the step's start (Notes, 1)."""
        self.stats["resting_contacts"] += self.settle_contacts(0.0, None)

    def settle_locally(self, t, seeds):
        """A slow contact mid-step: solve together the slow contacts of the particles ``seeds``
        and of the particles around them, instead of a cascade of tiny events."""
        x_seeds = self.position(np.asarray(seeds), t)
        found = self.tree.query_ball_point(x_seeds, LOCAL_REACH * self.r_max + 2 * self.speed * self.dt) \
            if self.tree is not None else [[]]
        members = np.unique(np.concatenate([np.asarray(seeds, np.int64)] + [np.asarray(f, np.int64) for f in found]))
        self.advance_to(members, t)
        v_before, w_before = self.v[members].copy(), self.state.omega[members].copy()
        self.settle_contacts(t, members)
        change = (np.abs(self.v[members] - v_before).max(1)
                  + self.radius[members] * np.abs(self.state.omega[members] - w_before).max(1))
        moved = change > 1e-6 * self.quiet  # below: the round-off of the solve, events stay valid
        for idx in members[moved & self.free[members]]:
            self.changed(int(idx), t)

    def settle_contacts(self, t, members) -> int:
        """Solve the slow contacts at time t among ``members`` (None: all): those touching, and
        those within ``rest_speed`` × the time left of touching (a face or another particle), so
        that none shuts within the step unseen. Returns their number."""
        horizon = self.dt - t
        contacts = self.touching_contacts(t, reach=self.settings.rest_speed * horizon, members=members)
        if not contacts or len(contacts["i"]) == 0:
            return 0
        u = self.relative_velocity(contacts)
        closing = -(u * contacts["normal"]).sum(1)
        touching = contacts["gap"] <= CONTACT_TOL * self.radius[contacts["i"]]
        # an edge or vertex at a gap is left to the events: the distance to it is not linear in time
        slow = (closing < self.settings.rest_speed) & (touching | contacts["face"] | ~contacts["wall"])
        contacts = self.deposit_touching({key: value[slow] for key, value in contacts.items()}, t)
        if len(contacts["i"]):
            self.solve_inelastic(contacts, horizon)
        return len(contacts["i"])

    def deposit_touching(self, c, t) -> dict:
        """Deposit the free particles of contacts ``c`` that touch a deposition wall or a deposited
        particle; the contacts, the deposited ones now of infinite mass."""
        if not c or len(c["i"]) == 0:
            return c
        i, j, k = c["i"], c["j"], c["k"]
        deposited = np.append(self.state.deposited, False)
        sticky = np.where(c["wall"], self.walls.deposition[k] if self.has_walls else False, deposited[j])
        sticky &= c["gap"] <= CONTACT_TOL * self.radius[i]
        for idx in np.unique(i[sticky & self.free[i]]):
            self.deposit(int(idx), t, reschedule=t > 0)
        return c

    def relative_velocity(self, c) -> np.ndarray:
        """(m, 3) contact-point velocity of body i relative to body j (or the wall)."""
        i, j, n = c["i"], c["j"], len(self.state)
        omega = self.state.omega
        u = self.v[i] + cross(omega[i], c["arm_i"]) - c["u_wall"]
        pj = j < n
        u[pj] -= self.v[j[pj]] + cross(omega[j[pj]], c["arm_j"][pj])
        return u

    def solve_inelastic(self, c, horizon):
        """Solve contacts ``c`` together: inelastic (e = 0), never pulling. Touching contacts
        have Coulomb friction (sticking within the cone, else sliding at μ λ_n); a contact with a
        gap may close it within ``horizon`` (s), not more, and an overlapping one opens at
        0.2 overlap / dt (so round-off never accumulates into sinking). Contacts that share
        no free particle are solved in closed form; the others by a direct solve of the touching
        ones (sticking first, then letting go or sliding where the impulse demands it) and a last
        solve of all normal impulses so that none approaches at the end. Then rolling friction at
        the wall contacts that stick."""
        c = unique_wall_contacts(c)
        m = len(c["i"])
        if m == 0:
            return
        gap = c["gap"]
        target = np.where(gap > 0, -gap / max(horizon, 1e-300), -0.2 * gap / self.dt)
        touching = gap <= CONTACT_TOL * self.radius[c["i"]]
        cs = ContactSet(c, self.v, self.state.omega, self.inv_mass, self.inv_inertia)
        cs.mu = np.where(touching, cs.mu, 0.0)  # no friction across a gap
        free = cs.inv_m > 0
        nb = len(cs.bodies)
        uses = np.bincount(cs.i[free[cs.i]], minlength=nb) + np.bincount(cs.j[free[cs.j]], minlength=nb)
        alone = (uses[cs.i] <= 1) & (uses[cs.j] <= 1)
        sticking = np.zeros(m, bool)
        rows = np.flatnonzero(alone)
        if len(rows):
            sticking[rows] = cs.closed_form(rows, target[rows]) & touching[rows]
        rows = np.flatnonzero(~alone)
        if len(rows):
            start = cs.v.copy(), cs.w.copy(), cs.lam_n.copy(), cs.lam_t.copy()
            at_stake = np.abs(cs.velocity(rows)).max() + np.abs(target).max() + self.settings.rest_speed
            stick_rows = rows[touching[rows]]
            if len(stick_rows):  # a static assembly in one direct solve
                cs.sticking_solve(stick_rows, target[stick_rows])
            tol = 1e-4 * self.settings.rest_speed if self.settings.rest_speed > 0 else 1e-12 * at_stake
            sticking[rows] = cs.gauss_seidel(rows, target[rows], GS_SWEEPS, tol) & touching[rows]
            solved = cs.normal_lcp(rows, target[rows])  # none approaches at the end
            # an ill-posed set (nearly dependent contacts) shows as a jump far beyond the speeds
            # at stake: fall back on sweeps, slower but never amplifying
            jump = np.abs(cs.v - start[0]).max()
            if not solved or not np.isfinite(jump) or jump > 10 * at_stake:
                cs.v, cs.w, cs.lam_n, cs.lam_t = (value.copy() for value in start)
                sticking[rows] = cs.jacobi(rows, target[rows], sweeps=500) & touching[rows]
                self.stats["fallbacks"] += 1
        bodies = cs.bodies[cs.real]
        self.v[bodies], self.state.omega[bodies] = cs.v[cs.real], cs.w[cs.real]
        rolling = np.flatnonzero(c["wall"] & (c["mu_r"] > 0) & (cs.lam_n > 0) & sticking)
        if len(rolling):
            self.roll_resistance(c["i"][rolling], c["normal"][rolling], c["u_wall"][rolling], cs.lam_n[rolling],
                                 c["mu_r"][rolling])
        if len(bodies):
            self.speed = max(self.speed, float(np.sqrt((self.v[bodies] ** 2).sum(1).max())))


    # -- a dense step: every contact of the step at once -------------------------------------------
    def step_contacts(self) -> dict:
        """Contacts that touch at the step's start or can close within it at the relative speed
        of their centres (the pair search reaches 2 × the largest speed × dt)."""
        return self.touching_contacts(0.0, reach=2 * self.speed * self.dt, closing_in=self.dt)

    def dense_step(self, c):
        """Solve every contact of the step at once (time-stepping contact dynamics), for beds and
        dense flows where events would cascade. Each contact gets a target normal velocity for
        the end of the step: a touching contact approaching faster than ``rest_speed`` rebounds
        with its restitution e (Newton's law), one that would close a gap g within the step
        rebounds so that its end-of-step separation is the one of the event solution,
        e (u dt − g) (target e u − (1 + e) g / dt), a slower one closes its gap but not more
        (−g / dt), an overlap opens at 0.2 overlap / dt. Impulses: normal >= 0, tangential in the
        Coulomb cone; projected Gauss–Seidel over the contacts one at a time (compiled:
        ``pmpm.contact_kernels``), at most ``dense_sweeps`` sweeps, warm-started from the impulses
        of the previous step (by particle ids). Then everything flies to the end of the step."""
        state, n, s = self.state, len(self.state), self.settings
        c = unique_wall_contacts(c)
        c = self.deposit_touching(c, 0.0)
        i, j, m = c["i"], c["j"], len(c["i"])
        dt = self.dt
        inv_m, inv_i = np.append(self.inv_mass, 0.0), np.append(self.inv_inertia, 0.0)
        V = np.vstack([self.v, np.zeros((1, 3))])
        W = np.vstack([state.omega, np.zeros((1, 3))])
        normal, arm_i, arm_j, u_wall, mu = c["normal"], c["arm_i"], c["arm_j"], c["u_wall"], c["mu"]
        e = np.full(m, s.restitution)
        if self.has_walls:
            e[c["wall"]] = self.walls.restitution[c["k"][c["wall"]]]
        closing = -(self.relative_velocity(c) * normal).sum(1)
        gap = c["gap"]
        bounce = np.where(closing > s.rest_speed, e, 0.0)
        target = np.maximum(np.where(gap > 0, -gap / dt, -0.2 * gap / dt),
                            bounce * closing - (1 + bounce) * np.maximum(gap, 0.0) / dt)
        # the sweep order: by first particle (rows follow the ids, so the order does not depend on
        # the tree search), then by the other particle, walls last
        order = np.lexsort((c["k"], j, i))
        i, j, normal, arm_i, arm_j, u_wall, mu, target, gap, closing = (
            a[order] for a in (i, j, normal, arm_i, arm_j, u_wall, mu, target, gap, closing))
        c = {key: value[order] for key, value in c.items()}
        r_i = np.sqrt((arm_i * arm_i).sum(1))  # spheres: the arms are −r_i n and r_j n
        r_j = np.sqrt((arm_j * arm_j).sum(1))
        lam_n, lam_t = self.warm_start(c)
        if lam_n.any():  # the previous step's impulses, projected on today's normals and cones
            lam_n = np.maximum(lam_n, 0.0)
            lam_t -= (lam_t * normal).sum(1)[:, None] * normal
            size = np.sqrt((lam_t * lam_t).sum(1))
            lam_t *= np.minimum(1.0, mu * lam_n / np.maximum(size, 1e-300))[:, None]
            J = lam_n[:, None] * normal + lam_t
            nJ = cross(normal, J)
            V += bincount3(i, J * inv_m[i, None], n + 1) - bincount3(j, J * inv_m[j, None], n + 1)
            W -= (bincount3(i, nJ * (inv_i[i] * r_i)[:, None], n + 1)
                  + bincount3(j, nJ * (inv_i[j] * r_j)[:, None], n + 1))
        tol = DENSE_TOL * s.rest_speed if s.rest_speed > 0 else 1e-9 * (np.abs(closing).max() + 1e-300)
        # without the previous step's impulses (the first dense step, a restart) a bed starts from
        # nothing: let the sweeps build its contact forces up once
        budget = s.dense_sweeps if self.remembered is not None else COLD_SWEEPS * s.dense_sweeps
        sweeps = projected_gauss_seidel(i, j, normal, r_i, r_j, u_wall, target, mu, inv_m, inv_i, V, W,
                                        lam_n, lam_t, budget, tol)
        self.v[:] = V[:n]
        state.omega[:] = W[:n]
        self.remember(c, lam_n, lam_t)
        active = lam_n > 0
        impact = active & (closing > s.rest_speed)
        wall = c["wall"]
        self.stats["particle_collisions"] += int((impact & ~wall).sum())
        self.stats["wall_collisions"] += int((impact & wall).sum())
        self.stats["resting_contacts"] += int((active & ~impact).sum())
        self.stats["dense_steps"] = 1
        self.stats["dense_contacts"] = m
        self.stats["sweeps"] = sweeps
        touching = gap <= CONTACT_TOL * self.radius[i]
        size = np.sqrt((lam_t * lam_t).sum(1))
        sticking = touching & active & (size < mu * lam_n * (1 - 1e-9))
        rolling = np.flatnonzero(wall & (c["mu_r"] > 0) & sticking)
        if len(rolling):
            self.roll_resistance(i[rolling], normal[rolling], u_wall[rolling], lam_n[rolling], c["mu_r"][rolling])

    def contact_keys(self, c) -> np.ndarray:
        """One integer per contact from the particle ids (a wall: its triangle), stable across steps."""
        ids = self.state.id
        other = np.where(c["wall"], -1 - c["k"], ids[np.minimum(c["j"], len(ids) - 1)])
        first, second = ids[c["i"]], other
        swap = ~c["wall"] & (first > second)
        first, second = np.where(swap, second, first), np.where(swap, first, second)
        return first.astype(np.int64) * (1 << 31) + (second.astype(np.int64) + (1 << 30))

    def warm_start(self, c):
        """Normal and tangential impulses (on i) of these contacts in the previous dense step."""
        m = len(c["i"])
        lam_n, lam_t = np.zeros(m), np.zeros((m, 3))
        memory = self.remembered
        if memory is None or len(memory.keys) == 0 or m == 0:
            return lam_n, lam_t
        keys, old_n, old_t, old_sign = memory.keys, memory.normal, memory.tangential, memory.sign
        now = self.contact_keys(c)
        at = np.minimum(np.searchsorted(keys, now), len(keys) - 1)
        found = keys[at] == now
        sign = self.key_sign(c)
        lam_n[found] = old_n[at[found]]
        lam_t[found] = old_t[at[found]] * (old_sign[at[found]] * sign[found])[:, None]
        return lam_n, lam_t

    def key_sign(self, c) -> np.ndarray:
        """+1 where contact i is the key's first particle, −1 where the pair was swapped."""
        ids = self.state.id
        pair = ~c["wall"]
        sign = np.ones(len(c["i"]))
        sign[pair] = np.where(ids[c["i"][pair]] > ids[c["j"][pair]], -1.0, 1.0)
        return sign

    def remember(self, c, lam_n, lam_t):
        keys = self.contact_keys(c)
        order = np.argsort(keys, kind="stable")
        self.memory = ContactMemory(keys[order], lam_n[order], lam_t[order], self.key_sign(c)[order])

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
            times = pair_contact_times(dx[near], dv[near], contact[near], self.end, self.quiet)
            self.push(times, 0, i[near], j[near], 0.0)
        if self.has_walls:
            self.push_wall_events(np.flatnonzero(self.free), 0.0)

    def schedule(self, i, t):
        """Recompute particle i's contacts from time t (its velocity just changed at t)."""
        horizon = self.end - t  # contacts at the very end of the step are the next step's
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
        """(particle, triangle) index pairs that may touch after moving ``travel`` (m, per particle):
        bounding spheres that meet, and a plane within reach on the domain side."""
        none = np.zeros(0, np.int64)
        if len(particles) == 0:
            return none, none
        x = self.state.x[particles]
        reach = self.radius[particles] + travel
        if len(particles) > 64:  # many particles: one search per triangle, within its own size
            k, row = flatten(cKDTree(x).query_ball_point(self.wall_centroid, self.wall_reach + reach.max()))
        else:
            row, k = flatten(self.wall_tree.query_ball_point(x, reach + self.wall_reach.max()))
        if len(k) == 0:
            return none, none
        d = x[row] - self.wall_centroid[k]
        height = (d * self.walls.normal[k]).sum(1)  # the centroid lies in the plane
        near = np.flatnonzero((np.sqrt((d * d).sum(1)) <= reach[row] + self.wall_reach[k])
                              & (height <= reach[row] + self.wall_travel[k])
                              & (height >= -self.radius[particles[row]] - self.wall_travel[k]))
        near = near[np.lexsort((k[near], row[near]))]  # by particle, then triangle: not the search's order
        return particles[row[near]], k[near]

    def push_wall_events(self, particles, t):
        """Queue the wall contacts of ``particles`` (all at their clock = t) from time t."""
        horizon = self.end - t  # contacts at the very end of the step are the next step's
        v = self.v[particles]
        i, k = self.wall_candidates(particles, np.sqrt((v * v).sum(1)) * horizon)
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
        if closing < s.rest_speed:
            return self.settle_locally(t, [i, j])
        e = s.restitution
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
        if closing < self.settings.rest_speed:
            return self.settle_locally(t, [i])
        inv_mass = self.inv_mass[i]
        J, _ = contact_impulse(u, n, inv_mass, 3.5 * inv_mass, walls.restitution[k], walls.friction[k])
        self.v[i] += inv_mass * J
        state.omega[i] += self.inv_inertia[i] * cross(arm, J)
        self.changed(i, t)

    def roll_resistance(self, i, n, u_wall, j_n, mu_r):
        """Rolling friction at resting wall contacts (arrays, one row per contact): the torque
        μ_r N r against rolling, with the rolling constraint kept, slows the rolling velocity
        relative to the wall by (5/7) μ_r J_n / m and the spin with it (Δω = n × Δv / r),
        never past a stop."""
        rolling = self.v[i] - u_wall
        rolling -= (rolling * n).sum(1)[:, None] * n
        speed = np.sqrt((rolling * rolling).sum(1))
        slow = np.minimum(5.0 / 7.0 * mu_r * j_n * self.inv_mass[i], speed)
        dv = -rolling * (slow / np.maximum(speed, 1e-300))[:, None]
        n_all = len(self.state)
        self.v += bincount3(i, dv, n_all)
        self.state.omega[:] += bincount3(i, cross(n, dv) / self.radius[i, None], n_all)


def unique_wall_contacts(c) -> dict:
    """Keep one of the wall contacts of a particle whose normals are (nearly) parallel, the
    closest: a sphere over the shared edge of two coplanar triangles touches both at one point,
    and near it the edge of the other triangle lies within the contact tolerance at a slightly
    tilted normal. Nearly parallel constraints would make the contact solve ill-posed."""
    if not c or c["wall"].sum() < 2:
        return c
    walls = np.flatnonzero(c["wall"])
    walls = walls[np.lexsort((c["gap"][walls], ~c["face"][walls], c["i"][walls]))]  # per particle: faces, closest first
    owner, normal = c["i"][walls], c["normal"][walls]
    drop = np.zeros(len(walls), bool)
    for shift in range(1, len(walls)):  # compare with the contacts ranked before, same particle
        same = owner[shift:] == owner[:-shift]
        if not same.any():
            break
        parallel = same & ((normal[shift:] * normal[:-shift]).sum(1) > PARALLEL)
        drop[shift:] |= parallel
    if not drop.any():
        return c
    keep = np.ones(len(c["i"]), bool)
    keep[walls[drop]] = False
    return {name: value[keep] for name, value in c.items()}


class ContactSet:
    """Contacts among a few bodies, solved inelastically (e = 0) with Coulomb friction.

    Works on local copies of the bodies' velocities (``bodies``: particle indices, n = a wall: a
    body of infinite mass at rest whose surface motion enters through ``u_wall``).
    """

    def __init__(self, c, v, omega, inv_mass, inv_inertia):
        n, m = len(v), len(c["i"])
        self.bodies, inverse = np.unique(np.concatenate([c["i"], c["j"]]), return_inverse=True)
        self.i, self.j = inverse[:m], inverse[m:]
        self.real = self.bodies < n
        nb, rows = len(self.bodies), self.bodies[self.real]
        self.v, self.w, self.inv_m, self.inv_i = np.zeros((nb, 3)), np.zeros((nb, 3)), np.zeros(nb), np.zeros(nb)
        self.v[self.real], self.w[self.real] = v[rows], omega[rows]
        self.inv_m[self.real], self.inv_i[self.real] = inv_mass[rows], inv_inertia[rows]
        self.normal, self.arm_i, self.arm_j = c["normal"], c["arm_i"], c["arm_j"]
        self.u_wall, self.mu = c["u_wall"], c["mu"]
        self.lam_n, self.lam_t = np.zeros(m), np.zeros((m, 3))

    def velocity(self, rows) -> np.ndarray:
        """(k, 3) contact-point velocity of body i relative to body j (or the wall)."""
        i, j = self.i[rows], self.j[rows]
        return (self.v[i] + cross(self.w[i], self.arm_i[rows]) - self.v[j] - cross(self.w[j], self.arm_j[rows])
                - self.u_wall[rows])

    def apply(self, rows, J) -> None:
        """Impulses J (k, 3) on bodies i, −J on bodies j of contacts ``rows``."""
        nb, i, j = len(self.bodies), self.i[rows], self.j[rows]
        self.v += bincount3(i, J * self.inv_m[i, None], nb) - bincount3(j, J * self.inv_m[j, None], nb)
        self.w += (bincount3(i, cross(self.arm_i[rows], J) * self.inv_i[i, None], nb)
                   - bincount3(j, cross(self.arm_j[rows], J) * self.inv_i[j, None], nb))
        j_n = (J * self.normal[rows]).sum(1)
        self.lam_n[rows] += j_n
        self.lam_t[rows] += J - j_n[:, None] * self.normal[rows]

    def closed_form(self, rows, target) -> np.ndarray:
        """Contacts that share no free body: exact impulses; returns the sticking flags."""
        i, j, normal = self.i[rows], self.j[rows], self.normal[rows]
        w_n = self.inv_m[i] + self.inv_m[j]
        k_t = (w_n + self.inv_i[i] * (self.arm_i[rows] ** 2).sum(1) + self.inv_i[j] * (self.arm_j[rows] ** 2).sum(1))
        u = self.velocity(rows)
        u_n = (u * normal).sum(1)
        lam_n = np.maximum((target - u_n) / w_n, 0.0)
        stick = -(u - u_n[:, None] * normal) / k_t[:, None]
        size = np.sqrt((stick * stick).sum(1))
        sticking = size <= self.mu[rows] * lam_n
        scale = np.where(sticking, 1.0, self.mu[rows] * lam_n / np.maximum(size, 1e-300))
        self.apply(rows, lam_n[:, None] * normal + stick * scale[:, None])
        return sticking

    def jacobi(self, rows, target, sweeps) -> np.ndarray:
        """Coupled contacts, robustly: Jacobi sweeps, each body's mass shared among its contacts
        (mass splitting), on accumulated impulses clamped to λ_n >= 0 and the Coulomb cone.
        Returns the sticking flags."""
        i, j, normal, mu = self.i[rows], self.j[rows], self.normal[rows], self.mu[rows]
        nb = len(self.bodies)
        free = self.inv_m > 0
        uses = np.bincount(i[free[i]], minlength=nb) + np.bincount(j[free[j]], minlength=nb)
        w_n = uses[i] * self.inv_m[i] + uses[j] * self.inv_m[j]
        k_t = (w_n + uses[i] * self.inv_i[i] * (self.arm_i[rows] ** 2).sum(1)
               + uses[j] * self.inv_i[j] * (self.arm_j[rows] ** 2).sum(1))
        lam_n, lam_t = np.zeros(len(i)), np.zeros((len(i), 3))
        for _ in range(sweeps):
            u = self.velocity(rows)
            u_n = (u * normal).sum(1)
            new_n = np.maximum(lam_n + (target - u_n) / w_n, 0.0)
            trial = lam_t - (u - u_n[:, None] * normal) / k_t[:, None]
            size = np.sqrt((trial * trial).sum(1))
            new_t = trial * np.minimum(1.0, mu * new_n / np.maximum(size, 1e-300))[:, None]
            J = (new_n - lam_n)[:, None] * normal + (new_t - lam_t)
            lam_n, lam_t = new_n, new_t
            self.apply(rows, J)
            if np.abs(J).max() * (self.inv_m[i] + self.inv_m[j]).max() <= 1e-9 * (np.abs(u).max() + 1e-300):
                break
        return np.sqrt((lam_t * lam_t).sum(1)) < mu * lam_n * (1 - 1e-9)

    def gauss_seidel(self, rows, target, sweeps, tol) -> np.ndarray:
        """Coupled contacts with friction: projected Gauss–Seidel sweeps over the contacts, one at
        a time (``pmpm.contact_kernels``), on the impulses accumulated so far (so a prior solve is
        the warm start), until no contact changes a velocity by more than ``tol`` (m/s). Returns
        the sticking flags."""
        lam_n, lam_t = self.lam_n[rows], self.lam_t[rows]  # copies (fancy indexing)
        r_i = np.sqrt((self.arm_i[rows] ** 2).sum(1))  # spheres: the arms are −r_i n and r_j n
        r_j = np.sqrt((self.arm_j[rows] ** 2).sum(1))
        projected_gauss_seidel(self.i[rows], self.j[rows], self.normal[rows], r_i, r_j, self.u_wall[rows], target,
                               self.mu[rows], self.inv_m, self.inv_i, self.v, self.w, lam_n, lam_t, sweeps, tol)
        self.lam_n[rows], self.lam_t[rows] = lam_n, lam_t
        size = np.sqrt((lam_t * lam_t).sum(1))
        return size < self.mu[rows] * lam_n * (1 - 1e-9)

    def jacobian(self, rows, normal_only=False):
        """Sparse map from the bodies' (v, ω) to the contacts' relative velocities: per contact
        and body ±[I | −[a]×] (3 rows), or only its normal row ±[n, a × n]."""
        i, j, k, nb = self.i[rows], self.j[rows], len(rows), len(self.bodies)
        entries = []
        for body, arm, sign in ((i, self.arm_i[rows], 1.0), (j, self.arm_j[rows], -1.0)):
            cols = 6 * body[:, None] + np.arange(6)
            if normal_only:
                n = self.normal[rows]
                entries.append((np.repeat(np.arange(k), 6), cols.ravel(),
                                (sign * np.column_stack([n, cross(arm, n)])).ravel()))
                continue
            one, zero = np.ones(k), np.zeros(k)
            block = np.stack([np.stack([one, zero, zero, zero, arm[:, 2], -arm[:, 1]], 1),
                              np.stack([zero, one, zero, -arm[:, 2], zero, arm[:, 0]], 1),
                              np.stack([zero, zero, one, arm[:, 1], -arm[:, 0], zero], 1)], 1)
            entries.append(((3 * np.arange(k)[:, None, None] + np.arange(3)[None, :, None]
                             + np.zeros((1, 1, 6), np.int64)).ravel(),
                            np.broadcast_to(cols[:, None, :], (k, 3, 6)).ravel(), (sign * block).ravel()))
        r, q, d = (np.concatenate(parts) for parts in zip(*entries))
        shape = ((1 if normal_only else 3) * k, 6 * nb)
        inv6 = np.repeat(np.column_stack([self.inv_m, self.inv_i]), 3, axis=1).ravel()
        if shape[0] <= DENSE_ROWS:
            jac = np.zeros(shape)
            jac[r, q] = d  # one body per column within a row: no repeated entries
            W = (jac * inv6) @ jac.T
            W[np.diag_indices(shape[0])] += 1e-10 * max(W.diagonal().max(), 1e-300)
            return W
        jac = sparse.csr_matrix((d, (r, q)), shape=shape)
        W = (jac @ sparse.diags(inv6) @ jac.T).tocsc()
        return W + sparse.identity(W.shape[0], format="csc") * (1e-10 * max(W.diagonal().max(), 1e-300))

    def sticking_solve(self, rows, target) -> np.ndarray:
        """Coupled contacts with friction, by a direct solve: first every contact sticks (its
        relative velocity becomes target·n); contacts whose impulse would pull let go, those
        outside the Coulomb cone slide (impulse λ_n (n + μ f), f fixed from the sticking guess),
        and the rest is solved again, until no contact changes (each one changes at most twice;
        letting go is settled before any cone is judged).
        Returns the sticking flags."""
        k = len(rows)
        normal, mu = self.normal[rows], self.mu[rows]
        W = self.jacobian(rows)
        dense = isinstance(W, np.ndarray)
        u = self.velocity(rows)
        status = np.zeros(k, np.int8)  # 0 sticking, 1 sliding, 2 let go
        direction = np.zeros((k, 3))
        impulse = np.zeros((k, 3))
        for _ in range(2 * k + 1):
            stick, slide = np.flatnonzero(status == 0), np.flatnonzero(status == 1)
            impulse = np.zeros((k, 3))
            if len(stick) + len(slide):
                # unknowns: 3 per sticking contact, λ_n per sliding one; P maps them to impulses
                n_stick = 3 * len(stick)
                rows_p = np.concatenate([(3 * stick[:, None] + np.arange(3)).ravel(),
                                         (3 * slide[:, None] + np.arange(3)).ravel()])
                cols_p = np.concatenate([np.arange(n_stick), np.repeat(n_stick + np.arange(len(slide)), 3)])
                d = normal[slide] + mu[slide, None] * direction[slide]
                p_vals = np.concatenate([np.ones(n_stick), d.ravel()])
                e_vals = np.concatenate([np.ones(n_stick), normal[slide].ravel()])
                size = (3 * k, n_stick + len(slide))
                if dense:
                    P, E = np.zeros(size), np.zeros(size[::-1])
                    P[rows_p, cols_p], E[cols_p, rows_p] = p_vals, e_vals
                    A = E @ W @ P
                else:
                    P = sparse.csr_matrix((p_vals, (rows_p, cols_p)), shape=size)
                    E = sparse.csr_matrix((e_vals, (cols_p, rows_p)), shape=size[::-1])
                    A = (E @ W @ P).tocsc()
                rhs = E @ (target[:, None] * normal - u).ravel()
                z = np.linalg.solve(A, rhs) if dense else np.atleast_1d(spsolve(A, rhs))
                impulse = (P @ z).reshape(k, 3)
            lam_n = (impulse * normal).sum(1)
            tang = impulse - lam_n[:, None] * normal
            size = np.sqrt((tang * tang).sum(1))
            pulls = (status < 2) & (lam_n < 0)
            if pulls.any():  # first let go where the contact would pull, then judge the cones
                status[pulls] = 2
                continue
            slides = (status == 0) & (size > mu * lam_n * (1 + 1e-9))
            if not slides.any():
                break
            status[slides] = 1
            direction[slides] = tang[slides] / size[slides, None]
        self.apply(rows, impulse)
        return status == 0

    def normal_lcp(self, rows, target) -> bool:
        """Make every contact of ``rows`` stop approaching (normal velocity >= target) with
        non-negative normal impulses: an active-set solve of W_nn λ = target − u_n, W_nn the
        normal-normal block of J M⁻¹ Jᵀ. Returns False (and applies nothing) if the active set
        does not settle."""
        i, j, normal = self.i[rows], self.j[rows], self.normal[rows]
        k = len(i)
        W = self.jacobian(rows, normal_only=True)
        dense = isinstance(W, np.ndarray)
        u_n = (self.velocity(rows) * normal).sum(1)
        tol = 1e-12 * (np.abs(u_n).max() + np.abs(target).max())
        active = u_n < target - tol
        lam, converged = np.zeros(k), False
        for _ in range(4 * k + 4):
            lam = np.zeros(k)
            if active.any():
                rhs = (target - u_n)[active]
                lam[active] = (np.linalg.solve(W[np.ix_(active, active)], rhs) if dense
                               else np.atleast_1d(spsolve(W[active][:, active].tocsc(), rhs)))
            after = u_n + W @ lam
            drop = active & (lam < 0)
            add = ~active & (after < target - tol)
            if not drop.any() and not add.any():
                converged = True
                break
            active = (active & ~drop) | (add if not drop.any() else False)
        if converged and lam.any():
            self.apply(rows, lam[:, None] * normal)
        return converged



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
    p, k = flatten(found)
    out = np.full(len(x), np.inf)
    if len(p):
        q, _ = closest_points_on_triangles(x[p], walls.a[k], walls.b[k], walls.c[k])
        d = np.linalg.norm(x[p] - q, axis=1)
        order = np.lexsort((d, p))  # nearest first within each point
        first = np.ones(len(p), bool)
        first[1:] = p[order][1:] != p[order][:-1]
        out[p[order][first]] = d[order][first]
    return out


def flatten(found) -> tuple[np.ndarray, np.ndarray]:
    """A k-d tree's per-point lists of neighbours as (point, neighbour) index arrays."""
    sizes = np.fromiter(map(len, found), np.int64, len(found))
    row = np.repeat(np.arange(len(found)), sizes)
    return row, np.fromiter(chain.from_iterable(found), np.int64, int(sizes.sum()))


def overlaps_existing(state: ParticleState, new) -> np.ndarray:
    """(len(new),) bool: new particles that overlap a particle of ``state`` or an earlier new one
    that is kept."""
    m = len(new)
    bad = np.zeros(m, bool)
    if m == 0:
        return bad
    if len(state):
        found = cKDTree(state.x).query_ball_point(new.x, float(state.radius.max()) + new.radius)
        i, k = flatten(found)
        close = np.linalg.norm(state.x[k] - new.x[i], axis=1) < (state.radius[k] + new.radius[i]) * (1 - 1e-9)
        bad[i[close]] = True
    if m > 1:
        pairs = cKDTree(new.x).query_pairs(2 * float(new.radius.max()), output_type="ndarray")
        pairs = np.sort(pairs, axis=1)
        d = np.linalg.norm(new.x[pairs[:, 0]] - new.x[pairs[:, 1]], axis=1)
        pairs = pairs[d < (new.radius[pairs[:, 0]] + new.radius[pairs[:, 1]]) * (1 - 1e-9)]
        for i, j in pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]:  # the few overlapping pairs, in order
            if not bad[i]:
                bad[j] = True
    return bad


def fmt(vector) -> str:
    return "(" + ", ".join(f"{float(v):.6g}" for v in vector) + ")"
