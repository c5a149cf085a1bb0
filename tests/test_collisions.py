"""Hard-sphere collisions (paper eq. 3-8) against rigid-body mechanics, one analytic number each."""
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pmpm.case import Section
from pmpm.collisions import (CollisionSettings, ContactMemory, Walls, advance_with_collisions, build_walls,
                             check_initial_particles, closest_points_on_triangles, closing_pairs, collision_settings,
                             contact_impulse, overlaps_existing, projected_gauss_seidel)
from pmpm.errors import CaseError
from pmpm.injection import NewParticles
from pmpm.particles import FIXED, ParticleState

G = 9.81


def particles(x, v=None, radius=0.01, density=1000.0, omega=None, motion=None) -> ParticleState:
    x = np.array(x, float).reshape(-1, 3)
    n = len(x)
    return ParticleState.empty().appended(np.arange(n), x, np.zeros((n, 3)) if v is None else np.array(v, float).reshape(n, 3),
                 np.zeros((n, 3)) if omega is None else np.array(omega, float).reshape(n, 3),
                 np.broadcast_to(np.asarray(radius, float), n).copy(),
                 np.broadcast_to(np.asarray(density, float), n).copy(),
                 np.zeros(n, np.int8) if motion is None else np.asarray(motion, np.int8))


def rectangle(origin, edge1, edge2, **kwargs) -> Walls:
    """A parallelogram of two triangles (sharing the diagonal origin → origin+edge1+edge2)."""
    o, e1, e2 = (np.asarray(v, float) for v in (origin, edge1, edge2))
    return Walls.from_triangles([[o, o + e1, o + e1 + e2], [o, o + e1 + e2, o + e2]], **kwargs)


def floor(**kwargs) -> Walls:
    """The plane z = 0 over [-1, 1]², normal +z, made of two triangles."""
    return rectangle((-1, -1, 0), (2, 0, 0), (0, 2, 0), **kwargs)


def kinetic(state) -> float:
    return float(0.5 * np.sum(state.mass * np.sum(state.v ** 2, 1))
                 + 0.5 * np.sum(state.inertia * np.sum(state.omega ** 2, 1)))


def step_under_gravity(state, walls, dt, settings, memory=None, gravity=(0.0, 0.0, -G)):
    """What the time loop does: v += g dt for the free particles, then move with collisions (the
    contact solver's ``memory`` from the last step). Returns the ContactStep."""
    state.v[state.movable] += np.asarray(gravity) * dt
    return advance_with_collisions(state, walls, dt, settings, memory)


class TimeLoop:
    """What the time loop does each step: v += g dt for the free particles, then move with
    collisions, the contact memory and the (moved) walls carried to the next step."""

    def __init__(self, walls, dt, settings, gravity=(0.0, 0.0, -G)):
        self.walls, self.dt, self.settings, self.gravity = walls, dt, settings, gravity
        self.memory = None

    def step(self, state) -> dict:
        result = step_under_gravity(state, self.walls, self.dt, self.settings, self.memory, self.gravity)
        self.walls, self.memory = result.walls, result.memory
        return result.stats


# -- particle-particle -------------------------------------------------------------------------
@pytest.mark.parametrize("e", [1.0, 0.8, 0.0])
@pytest.mark.parametrize("densities", [(1000.0, 1000.0), (1000.0, 3000.0)])
def test_head_on(e, densities):
    """Post-impact velocities of a head-on impact: exact to 1e-12; momentum kept; KE ratio e² in
    the centre-of-mass frame."""
    state = particles([[0, 0, 0], [0.05, 0, 0]], [[1.0, 0, 0], [-0.5, 0, 0]], radius=0.01, density=densities)
    m1, m2 = state.mass
    u1, u2 = 1.0, -0.5
    p_before = state.mass @ state.v
    vc = (m1 * u1 + m2 * u2) / (m1 + m2)
    ke_rel_before = 0.5 * m1 * (u1 - vc) ** 2 + 0.5 * m2 * (u2 - vc) ** 2
    stats = advance_with_collisions(state, None, 0.1, CollisionSettings(restitution=e, friction=0.3)).stats
    v1 = (m1 * u1 + m2 * u2 + m2 * e * (u2 - u1)) / (m1 + m2)
    v2 = (m1 * u1 + m2 * u2 + m1 * e * (u1 - u2)) / (m1 + m2)
    assert stats["particle_collisions"] == 1
    assert abs(state.v[0, 0] - v1) < 1e-12 and abs(state.v[1, 0] - v2) < 1e-12
    assert np.allclose(state.mass @ state.v, p_before, rtol=0, atol=1e-15)
    ke_rel_after = 0.5 * m1 * (state.v[0, 0] - vc) ** 2 + 0.5 * m2 * (state.v[1, 0] - vc) ** 2
    assert ke_rel_after == pytest.approx(e ** 2 * ke_rel_before, rel=1e-12, abs=1e-18)
    # contact at t_c = 0.03 / 1.5 = 0.02 s, then free flight (eq. 8): positions exact
    assert state.x[0, 0] == pytest.approx(0.02 * u1 + 0.08 * v1, abs=1e-13)
    assert np.all(state.omega == 0)


def test_newtons_cradle():
    """Five touching equal balls, the first hit by a sixth: only the last one leaves, at 1 m/s."""
    r = 0.01
    x = [[-0.05, 0, 0]] + [[2 * r * k, 0, 0] for k in range(5)]
    v = [[1.0, 0, 0]] + [[0, 0, 0]] * 5
    state = particles(x, v, radius=r)
    stats = advance_with_collisions(state, None, 0.05, CollisionSettings(restitution=1.0, friction=0.0)).stats
    assert stats["particle_collisions"] == 5
    assert np.allclose(state.v[:-1], 0.0, atol=1e-12)
    assert np.allclose(state.v[-1], [1.0, 0, 0], atol=1e-12)


@pytest.mark.parametrize("mu", [0.05, 1.0])
def test_oblique_pair_momentum_and_angular_momentum(mu):
    """Oblique impact of unequal spheres with friction: the analytic impulse (sliding for small μ,
    sticking for large μ, 2/7 m* u_t), linear and angular momentum conserved to 1e-12."""
    r1, r2 = 0.01, 0.02
    state = particles([[0, 0, 0], [0.05, 0.02, 0]], [[2.0, 0.0, 0.3], [-1.0, 0.0, 0.0]],
                      radius=[r1, r2], density=[1000.0, 2500.0], omega=[[0, 0, 30.0], [5.0, 0, 0]])
    e = 0.7
    m = state.mass
    I = state.inertia

    def angular_momentum(s):
        return np.sum(np.cross(s.x, s.v * s.mass[:, None]) + s.omega * s.inertia[:, None], axis=0)

    # contact: solve eq. 7 here independently
    dx, dv = state.x[0] - state.x[1], state.v[0] - state.v[1]
    a, b, c = dv @ dv, dx @ dv, dx @ dx - (r1 + r2) ** 2
    tc = (-b - np.sqrt(b * b - a * c)) / a
    n = (dx + dv * tc) / (r1 + r2)
    u = (state.v[0] + np.cross(state.omega[0], -r1 * n)) - (state.v[1] + np.cross(state.omega[1], r2 * n))
    un = u @ n
    ut = u - un * n
    mstar = 1 / (1 / m[0] + 1 / m[1])
    jn = -(1 + e) * mstar * un
    jt_stick = -ut / (3.5 / mstar)
    sticking = np.linalg.norm(jt_stick) <= mu * jn
    jt = jt_stick if sticking else -mu * jn * ut / np.linalg.norm(ut)
    J = jn * n + jt
    expect_v0, expect_v1 = state.v[0] + J / m[0], state.v[1] - J / m[1]
    expect_w0 = state.omega[0] + np.cross(-r1 * n, J) / I[0]
    expect_w1 = state.omega[1] + np.cross(r2 * n, -J) / I[1]
    p0, L0 = state.mass @ state.v, angular_momentum(state)

    advance_with_collisions(state, None, 0.05, CollisionSettings(restitution=e, friction=mu))
    assert sticking == (mu == 1.0)
    assert np.allclose(state.v, [expect_v0, expect_v1], rtol=0, atol=1e-12)
    assert np.allclose(state.omega, [expect_w0, expect_w1], rtol=0, atol=1e-10)
    assert np.allclose(state.mass @ state.v, p0, rtol=0, atol=1e-15)
    assert np.allclose(angular_momentum(state), L0, rtol=0, atol=1e-15)


def test_fixed_particle_has_infinite_mass():
    """A ball bouncing off a fixed ball: reflected with e, the fixed one neither moves nor spins."""
    state = particles([[0, 0, 0], [0.05, 0, 0]], [[1.0, 0, 0], [0, 0, 0]], motion=[0, FIXED])
    advance_with_collisions(state, None, 0.05, CollisionSettings(restitution=0.5, friction=0.3))
    assert state.v[0, 0] == pytest.approx(-0.5, abs=1e-12)
    assert np.all(state.x[1] == [0.05, 0, 0]) and np.all(state.v[1] == 0) and np.all(state.omega[1] == 0)


# -- particle-wall -----------------------------------------------------------------------------
@pytest.mark.parametrize("mu", [0.05, 1.0])
def test_oblique_wall_impact(mu):
    """Sphere on a fixed floor, incoming (vx, 0, −vz): sliding keeps vx − μ(1+e)vz and spins up to
    ω_y = 5/2 μ (1+e) vz / r; sticking leaves vx 5/7 of its value, rolling (ω_y = vx'/r)."""
    r, e, vx, vz = 0.01, 0.6, 1.0, 0.5
    state = particles([[0, 0, 0.02]], [[vx, 0, -vz]], radius=r)
    advance_with_collisions(state, floor(restitution=e, friction=mu), 0.05, CollisionSettings())
    assert state.v[0, 2] == pytest.approx(e * vz, abs=1e-12)
    if mu * (1 + e) * vz < 2 / 7 * vx:  # sliding
        assert mu == 0.05
        assert state.v[0, 0] == pytest.approx(vx - mu * (1 + e) * vz, abs=1e-12)
        assert state.omega[0, 1] == pytest.approx(2.5 * mu * (1 + e) * vz / r, abs=1e-9)
    else:
        assert state.v[0, 0] == pytest.approx(5 / 7 * vx, abs=1e-12)
        assert state.omega[0, 1] == pytest.approx(5 / 7 * vx / r, abs=1e-9)


def test_shared_edge_collides_once():
    """Straight onto the diagonal shared by the floor's two triangles: one impulse, v_z = e v."""
    state = particles([[0.3, 0.3, 0.02]], [[0, 0, -1.0]])
    stats = advance_with_collisions(state, floor(restitution=0.5), 0.05, CollisionSettings()).stats
    assert stats["wall_collisions"] == 1
    assert np.allclose(state.v[0], [0, 0, 0.5], atol=1e-12)


def test_edge_and_vertex_contacts():
    """A ball hitting a triangle's edge or vertex side-on bounces along the contact normal."""
    tri = Walls.from_triangles([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], restitution=1.0, friction=0.0)
    # edge x+y=1, approached in-plane (z = 0) along its normal
    s = np.sqrt(0.5)
    state = particles([[0.5 + 0.05 * s, 0.5 + 0.05 * s, 0.0]], [[-s, -s, 0]], radius=0.01)
    advance_with_collisions(state, tri, 0.1, CollisionSettings())
    assert np.allclose(state.v[0], [s, s, 0], atol=1e-12)
    # vertex (1, 0, 0), approached along +x from beyond it, 45° above the plane
    d = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    state = particles([[1 + 0.05 * d[0], 0, 0.05 * d[2]]], [-d], radius=0.01)
    advance_with_collisions(state, tri, 0.1, CollisionSettings())
    assert np.allclose(state.v[0], d, atol=1e-12)


def test_bouncing_ball_rebound_heights():
    """Dropped on a floor under gravity: each apex height (above contact) is e² of the previous
    one, within 0.5 % (time step 1e-4 s, first-order in dt), then the ball comes to rest."""
    r, e, dt = 0.01, 0.8, 1e-4
    state = particles([[0, 0, 0.3 + r]], radius=r)
    walls, settings = floor(restitution=e), CollisionSettings(rest_speed=3 * G * dt)
    apexes, rising, top = [], False, 0.0
    memory = None
    for _ in range(10000):
        memory = step_under_gravity(state, walls, dt, settings, memory).memory
        if state.v[0, 2] > 0:
            rising, top = True, max(top, state.x[0, 2])
        elif rising:
            apexes.append(top - r)
            rising, top = False, 0.0
    heights = np.array([0.3] + apexes[:4])
    assert np.allclose(heights[1:] / heights[:-1], e ** 2, rtol=5e-3)


def test_resting_ball_does_not_sink_or_gain_energy():
    """A ball resting on the floor for 10⁴ steps: overlap < 1e-6 d, no upward motion, no energy."""
    r, dt = 0.01, 1e-3
    state = particles([[0.1, 0.2, r]], radius=r)
    walls, settings = floor(restitution=0.9), CollisionSettings(rest_speed=3 * G * dt)
    lowest, highest, energy = r, r, 0.0
    memory = None
    for _ in range(10000):
        result = step_under_gravity(state, walls, dt, settings, memory)
        memory, stats = result.memory, result.stats
        lowest, highest = min(lowest, state.x[0, 2]), max(highest, state.x[0, 2])
        energy = max(energy, kinetic(state))
        assert not stats["capped"]
    assert r - lowest < 1e-6 * 2 * r
    assert highest - r < 1e-6 * 2 * r
    assert energy < 1e-20
    assert np.allclose(state.x[0, :2], [0.1, 0.2], atol=1e-15)


def test_resting_column_and_bed():
    """Three stacked balls and a small bed of 8 touching balls on a floor: after 2000 steps none
    sinks into the floor or into another by more than 1e-6 d, and none moves."""
    r, dt = 0.01, 1e-3
    column = [[0, 0, r], [0, 0, 3 * r], [0, 0, 5 * r]]
    bed = [[2 * r * i, 2 * r * j + 0.1, r] for i in range(2) for j in range(2)]
    bed += [[r + 2 * r * i, 0.1 + r + 2 * r * j, r * (1 + np.sqrt(2))] for i in range(1) for j in range(1)]
    state = particles(column + bed, radius=r)
    start = state.x.copy()
    walls = floor(restitution=0.9, friction=0.5)
    settings = CollisionSettings(restitution=0.9, friction=0.5, rest_speed=3 * G * dt)
    memory = None
    for _ in range(2000):
        result = step_under_gravity(state, walls, dt, settings, memory)
        memory, stats = result.memory, result.stats
    dist = np.linalg.norm(state.x[:, None] - state.x[None], axis=2) + np.eye(len(state)) * 1e9
    assert dist.min() > 2 * r * (1 - 1e-6)
    assert state.x[:, 2].min() > r * (1 - 2e-6)
    assert np.abs(state.x - start).max() < 1e-6 * 2 * r
    assert not stats["capped"]


def test_ball_dropped_on_a_resting_column():
    """A ball dropped onto a column of three resting balls: it bounces, the column never sinks
    into the floor or itself by more than 1e-6 d, the energy (kinetic + potential) never grows,
    and in the end all four rest stacked."""
    r, dt = 0.01, 1e-3
    state = particles([[0, 0, r], [0, 0, 3 * r], [0, 0, 5 * r], [0, 0, 12 * r]], radius=r)
    walls = floor(restitution=0.6, friction=0.5)
    settings = CollisionSettings(restitution=0.6, friction=0.5, rest_speed=3 * G * dt)

    def energy():
        return kinetic(state) + G * float(state.mass @ state.x[:, 2])

    previous = energy()
    memory = None
    for _ in range(600):
        result = step_under_gravity(state, walls, dt, settings, memory)
        memory, stats = result.memory, result.stats
        now = energy()
        assert now <= previous + 1e-12 * abs(previous)
        previous = now
        gaps = np.diff(state.x[:, 2]) - 2 * r
        assert gaps.min() > -2e-6 * r and state.x[0, 2] > r * (1 - 2e-6)
        assert not stats["capped"]
    assert np.allclose(state.x[:, 2], [r, 3 * r, 5 * r, 7 * r], rtol=0, atol=1e-6 * r)
    assert kinetic(state) < 1e-12


def box(side, height, **kwargs) -> Walls:
    """An open box [0, side]² × [0, height]: floor and four sides, two triangles each."""
    parts = [rectangle((0, 0, 0), (side, 0, 0), (0, side, 0), **kwargs),
             rectangle((0, 0, 0), (0, 0, height), (side, 0, 0), **kwargs),
             rectangle((0, side, 0), (side, 0, 0), (0, 0, height), **kwargs),
             rectangle((0, 0, 0), (0, side, 0), (0, 0, height), **kwargs),
             rectangle((side, 0, 0), (0, 0, height), (0, side, 0), **kwargs)]
    fields = ("a", "b", "c", "normal", "boundary", "restitution", "friction", "rolling_friction", "velocity",
              "angular_velocity", "center", "rigid", "deposition")
    return Walls(*(np.concatenate([getattr(w, name) for w in parts]) for name in fields))


def test_pile_in_a_box_loses_energy():
    """27 balls poured into a box settle into a pile: the energy (kinetic + potential) never
    grows, no ball overlaps another or a wall by more than 1e-6 d, none leaves the box, and
    what kinetic energy is left after 0.5 s is under 1 % of the energy lost."""
    r, dt, side = 0.01, 1e-3, 0.08
    rng = np.random.default_rng(7)
    grid = np.arange(0.015, side - 0.01, 0.025)
    x = np.array([[a, b, z] for z in (0.03, 0.06, 0.09) for a in grid for b in grid])
    n = len(x)
    x += rng.uniform(-1e-3, 1e-3, (n, 3))
    state = particles(x, rng.normal(0, 0.2, (n, 3)), radius=r)
    walls = box(side, 0.5, restitution=0.5, friction=0.5)
    settings = CollisionSettings(restitution=0.5, friction=0.5, rest_speed=3 * G * dt)

    def energy():
        return kinetic(state) + G * float(state.mass @ state.x[:, 2])

    previous = start = energy()
    memory = None
    for _ in range(500):
        result = step_under_gravity(state, walls, dt, settings, memory)
        memory, stats = result.memory, result.stats
        now = energy()
        assert now <= previous + 1e-9 * abs(previous)
        previous = now
        assert not stats["capped"]
    dist = np.linalg.norm(state.x[:, None] - state.x[None], axis=2) + np.eye(n)
    assert dist.min() > 2 * r * (1 - 1e-6)
    assert state.x[:, 2].min() > r * (1 - 2e-6)
    assert r * (1 - 2e-6) < state.x[:, :2].min() and state.x[:, :2].max() < side - r * (1 - 2e-6)
    assert kinetic(state) < 0.01 * (start - energy())


def test_rolling_down_a_slope():
    """A ball on a 30° slope (two triangles) with friction rolls without slipping: acceleration
    5/7 g sin θ within 2 %, across the triangles' shared diagonal, without sinking."""
    theta, r, dt = np.radians(30.0), 0.01, 1e-4
    down = np.array([np.cos(theta), 0.0, -np.sin(theta)])
    normal = np.array([np.sin(theta), 0.0, np.cos(theta)])
    walls = rectangle(-0.5 * down - np.array([0, 0.5, 0]), down, (0, 1, 0), restitution=0.5, friction=0.5)
    assert np.allclose(walls.normal, normal)
    start = -0.05 * down + r * normal + np.array([0, 0.02, 0])
    state = particles([start], radius=r)
    settings = CollisionSettings(rest_speed=3 * G * dt)
    memory = None
    for _ in range(2000):
        memory = step_under_gravity(state, walls, dt, settings, memory).memory
        assert abs((state.x[0] - walls.a[0]) @ normal - r) < 1e-6 * 2 * r
    t = 2000 * dt
    speed = state.v[0] @ down
    assert speed / t == pytest.approx(5 / 7 * G * np.sin(theta), rel=0.02)
    assert (state.x[0] - start) @ down > 0.05  # crossed the diagonal
    assert np.linalg.norm(state.v[0] + np.cross(state.omega[0], -r * normal)) < 1e-6  # rolling


def test_rolling_friction_deceleration():
    """A ball rolling on a floor with rolling friction μ_r slows by (5/7) μ_r g, within 1 %."""
    r, dt, mu_r, v0 = 0.01, 1e-4, 0.02, 1.0
    state = particles([[-0.5, 0, r]], [[v0, 0, 0]], radius=r, omega=[[0, v0 / r, 0]])
    walls = floor(restitution=0.5, friction=0.5, rolling_friction=mu_r)
    settings = CollisionSettings(rest_speed=3 * G * dt)
    memory = None
    for _ in range(5000):
        memory = step_under_gravity(state, walls, dt, settings, memory).memory
    t = 5000 * dt
    assert (v0 - state.v[0, 0]) / t == pytest.approx(5 / 7 * mu_r * G, rel=0.01)
    assert state.omega[0, 1] * r == pytest.approx(state.v[0, 0], rel=1e-9)


@pytest.mark.parametrize("mu_r", [0.0, 0.02])
def test_spin_about_the_contact_normal_stops_by_rolling_friction(mu_r):
    """A ball at rest on a floor, spinning about the vertical: a point contact holds no torque
    about its normal, so without rolling friction it spins on; with μ_r the rolling-friction torque
    μ_r N r slows it at 2.5 μ_r g / r (within 1 %) until it stops, and it stays stopped."""
    r, dt, spin = 0.01, 1e-4, 5.0
    state = particles([[0.0, 0.0, r]], radius=r, omega=[[0.0, 0.0, spin]])
    walls = floor(restitution=0.5, friction=0.5, rolling_friction=mu_r)
    settings = CollisionSettings(rest_speed=3 * G * dt)
    memory = None
    for _ in range(500):
        memory = step_under_gravity(state, walls, dt, settings, memory).memory
    slowing = 2.5 * mu_r * G / r
    assert (spin - state.omega[0, 2]) / (500 * dt) == pytest.approx(slowing, rel=0.01, abs=1e-12)
    if mu_r > 0:
        for _ in range(int(spin / slowing / dt)):
            memory = step_under_gravity(state, walls, dt, settings, memory).memory
        assert np.abs(state.omega[0]).max() < 1e-12 and np.abs(state.v[0]).max() < 1e-9


def test_conveyor_surface_drags_a_ball():
    """A ball at rest dropped gently on a belt moving at U (surface motion): with enough friction
    it rolls at 2/7 U after the first contact; the belt itself stays in place."""
    U, r = 1.0, 0.01
    walls = floor(restitution=0.0, friction=1.0, velocity=(U, 0, 0))
    before = walls.a.copy()
    state = particles([[0, 0, r + 1e-4]], [[0, 0, -1.0]], radius=r)
    advance_with_collisions(state, walls, 0.01, CollisionSettings())
    assert state.v[0, 0] == pytest.approx(2 / 7 * U, abs=1e-12)
    assert abs(state.v[0, 2]) < 1e-12
    assert np.all(walls.a == before)


def test_rigid_paddle_hits_a_ball():
    """A rigid plane paddle moving at U into a ball at rest: v = (1 + e) U exactly; the paddle has
    moved U dt at the end of the step and the gap is e U (dt − t_c)."""
    U, e, r, dt = 2.0, 0.5, 0.01, 0.01
    paddle = rectangle((0, -0.5, -0.5), (0, 1, 0), (0, 0, 1), restitution=e, friction=0.3,
                       velocity=(U, 0, 0), rigid=True)
    assert np.allclose(paddle.normal, [1, 0, 0])
    state = particles([[r + 0.005, 0, 0]], radius=r)
    result = advance_with_collisions(state, paddle, dt, CollisionSettings())
    stats, paddle = result.stats, result.walls
    assert stats["wall_collisions"] == 1
    assert np.allclose(state.v[0], [(1 + e) * U, 0, 0], rtol=0, atol=1e-12)
    assert np.allclose(paddle.a[:, 0], U * dt, atol=1e-15)
    tc = 0.005 / U
    assert state.x[0, 0] - r - paddle.a[0, 0] == pytest.approx(e * U * (dt - tc), abs=1e-12)


def test_rotating_paddle_hits_a_ball():
    """A rigid paddle rotating about z at Ω hits a ball at rest at distance ρ from the axis: the
    ball leaves at (1 + e) Ω ρ along the paddle normal (no friction), within 1e-3."""
    omega, e, r, rho, dt = 10.0, 1.0, 0.01, 0.3, 1e-3
    paddle = rectangle((0, 0, -0.5), (0, 0, 1), (1, 0, 0), restitution=e, friction=0.0,
                       angular_velocity=(0, 0, omega), center=(0, 0, 0), rigid=True)
    assert np.allclose(paddle.normal, [0, 1, 0])
    state = particles([[rho, r + 1e-3, 0]], radius=r)
    settings = CollisionSettings(restitution=e, friction=0.0)
    total = 0
    for _ in range(5):
        result = advance_with_collisions(state, paddle, dt, settings)
        total, paddle = total + result.stats["wall_collisions"], result.walls
    assert total == 1
    contact_radius = np.hypot(rho, r)
    assert np.linalg.norm(state.v[0]) == pytest.approx((1 + e) * omega * rho, rel=2e-2)
    assert state.v[0, 1] > 0 and contact_radius > 0


def test_deposition():
    """A ball hitting a deposition wall sticks there; a ball hitting it deposits as well."""
    r = 0.01
    walls = floor(deposition=True)
    state = particles([[0, 0, 0.015], [0, 0, 0.045]], [[0.3, 0, -1.0], [0, 0, -1.0]], radius=r)
    advance_with_collisions(state, walls, 0.05, CollisionSettings())
    assert state.deposited.all()
    assert np.all(state.v == 0) and np.all(state.omega == 0)
    assert state.x[0, 2] == pytest.approx(r, abs=1e-12)
    assert np.linalg.norm(state.x[1] - state.x[0]) == pytest.approx(2 * r, abs=1e-12)


def test_event_cap_finishes_the_step():
    """With a budget of 3 events the step still ends, reports the cap, and the contacts left are
    inelastic (no approach along any contact normal)."""
    r = 0.01
    state = particles([[0, 0, r], [0, 0, 3 * r], [0, 0, 5 * r], [0, 0, 7 * r]], [[0, 0, -0.1]] * 4, radius=r)
    settings = CollisionSettings(restitution=0.0, max_events_per_particle=0, min_events=3)
    stats = advance_with_collisions(state, floor(restitution=0.0), 1e-3, settings).stats
    assert stats["capped"] and stats["events"] == 3
    assert np.all(np.diff(state.v[:, 2]) >= -1e-9) and state.v[0, 2] >= -1e-9


# -- dense steps (every contact of the step solved at once) --------------------------------------
@pytest.mark.parametrize("e", [1.0, 0.5])
def test_dense_step_touching_pair(e):
    """A touching pair approaching at u, solved as a dense step: it leaves at e u, momentum and
    the centre of mass as without contact."""
    r, u, dt = 0.01, 0.3, 1e-3
    state = particles([[0, 0, 0], [2 * r, 0, 0]], [[u / 2, 0, 0], [-u / 2, 0, 0]], radius=r, density=[1000.0, 3000.0])
    p0 = state.mass @ state.v
    stats = advance_with_collisions(state, None, dt, CollisionSettings(restitution=e, friction=0.3, rest_speed=0.01,
                                                                         dense_contacts=1)).stats
    assert stats["dense_steps"] == 1 and stats["particle_collisions"] == 1
    assert state.v[1, 0] - state.v[0, 0] == pytest.approx(e * u, rel=1e-12)
    assert np.allclose(state.mass @ state.v, p0, rtol=0, atol=1e-15)
    assert np.allclose(state.v[:, 1:], 0) and np.allclose(state.omega, 0)


def test_dense_step_gap_closing_within_the_step():
    """A ball a gap g above the floor falling at u (u dt > g), as a dense step: at the end of the
    step its gap is e (u dt − g), the event solution's."""
    r, u, dt, g, e = 0.01, 1.0, 1e-3, 3e-4, 0.8
    state = particles([[0, 0, r + g]], [[0, 0, -u]], radius=r)
    settings = CollisionSettings(restitution=e, friction=0.3, rest_speed=0.01, dense_contacts=1)
    stats = advance_with_collisions(state, floor(restitution=e), dt, settings).stats
    assert stats["dense_steps"] == 1 and stats["wall_collisions"] == 1
    assert state.x[0, 2] - r == pytest.approx(e * (u * dt - g), rel=1e-9)


def test_dense_bed_rests():
    """Three layers of 10 × 10 touching balls on a floor, walled in: every step is a dense step,
    and after 200 steps under gravity no ball has moved or sunk by more than 1e-3 d."""
    r, dt, side = 0.01, 1e-3, 0.2
    grid = r + 2 * r * np.arange(10)
    x = np.array([[a, b, r + 2 * r * k] for k in range(3) for a in grid for b in grid])
    state = particles(x, radius=r)
    walls = box(side, 0.5, restitution=0.5, friction=0.5)
    settings = CollisionSettings(restitution=0.5, friction=0.5, rest_speed=3 * G * dt)
    memory = None
    for _ in range(200):
        result = step_under_gravity(state, walls, dt, settings, memory)
        memory, stats = result.memory, result.stats
        assert stats["dense_steps"] == 1 and not stats["capped"]
    assert np.abs(state.x - x).max() < 1e-3 * 2 * r
    pairs = np.linalg.norm(state.x[:, None] - state.x[None], axis=2) + np.eye(len(x))
    assert pairs.min() > 2 * r * (1 - 1e-3)


@pytest.mark.parametrize("mu", [0.05, 1.0])
def test_gauss_seidel_single_contact_is_the_closed_form(mu):
    """One contact alone: the compiled sweep gives the closed-form impulse (contact_impulse) in one
    update, sliding or sticking; a second sweep changes nothing."""
    r, m1, m2 = 0.01, 0.004, 0.012
    n = np.array([0.0, 0.0, 1.0])  # towards body 0
    inv_m, inv_i = np.array([1 / m1, 1 / m2]), np.array([2.5 / (m1 * r * r), 2.5 / (m2 * r * r)])
    v = np.array([[0.3, -0.1, -0.5], [0.0, 0.2, 0.4]])
    omega = np.array([[1.0, 0.0, 2.0], [0.0, -3.0, 0.0]])
    u = v[0] - v[1] - np.cross(r * omega[0] + r * omega[1], n)
    k_t = inv_m.sum() + (inv_i * r * r).sum()
    J, _ = contact_impulse(u, n, inv_m.sum(), k_t, 0.0, mu)
    lam_n, lam_t = np.zeros(1), np.zeros((1, 3))
    sweeps = projected_gauss_seidel(np.array([0]), np.array([1]), n[None], np.array([r]), np.array([r]),
                                    np.zeros((1, 3)), np.zeros(1), np.array([mu]), inv_m, inv_i, v, omega,
                                    lam_n, lam_t, 10, 1e-12)
    assert sweeps == 2
    assert np.allclose(lam_n[0] * n + lam_t[0], J, rtol=1e-12, atol=1e-18)
    after = v[0] - v[1] - np.cross(r * omega[0] + r * omega[1], n)
    assert after @ n == pytest.approx(0.0, abs=1e-15)


def test_closing_pairs_matches_the_direct_filter():
    """The compiled pair filter of the dense step against the same conditions in numpy."""
    rng = np.random.default_rng(3)
    n = 400
    x, v = rng.uniform(0, 0.1, (n, 3)), rng.normal(0, 0.5, (n, 3))
    radius, free = rng.uniform(0.002, 0.004, n), rng.random(n) > 0.2
    pairs = cKDTree(x).query_pairs(0.012, output_type="ndarray")
    reach, horizon, tol = 0.004, 2e-3, 1e-6
    keep = closing_pairs(pairs, x, v, radius, free, reach, horizon, tol)
    i, j = pairs.T
    gap = np.linalg.norm(x[i] - x[j], axis=1) - radius[i] - radius[j]
    direct = ((free[i] | free[j]) & (gap <= tol * (radius[i] + radius[j]) + reach)
              & (gap <= np.linalg.norm(v[i] - v[j], axis=1) * horizon + tol * radius[i]))
    assert 0 < keep.sum() < len(pairs) and np.array_equal(keep, direct)


# -- set-up helpers ----------------------------------------------------------------------------
def fake_case(**sections):
    base = dict(path=Path("case.toml"), boundaries={}, collisions=None, deposition=None, coupling=None,
                run=Section({"dt": 1e-3, "gravity": (0.0, 0.0, -G)}))
    base.update(sections)
    return SimpleNamespace(**base)


class FakeMesh:
    """A unit cube's six sides, two triangles each, normals inwards."""

    boundary_names = ["xmin", "xmax", "ymin", "ymax", "zmin", "zmax"]

    def boundary_triangles(self, names):
        tris, index, normals = [], [], []
        for name in names:
            b = self.boundary_names.index(name)
            axis, side = b // 2, b % 2
            n = np.zeros(3)
            n[axis] = -1.0 if side else 1.0
            u, w = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
            o = np.eye(3)[axis] * side
            for tri in ([o, o + u, o + u + w], [o, o + u + w, o + w]):
                tris.append(tri)
                index.append(b)
                normals.append(n)
        return np.array(tris), np.array(index), np.array(normals)


def test_build_walls_and_settings():
    """Walls: unlisted boundaries are fixed walls; an inlet that lets particles pass is left out;
    overrides and deposition."""
    case = fake_case(
        boundaries={"xmin": Section({"type": "inlet", "particles": "pass"}),
                    "zmin": Section({"type": "wall", "restitution": 0.2, "friction": None, "rolling_friction": None,
                                     "velocity": (1.0, 0, 0), "angular_velocity": (0, 0, 0),
                                     "center": (0, 0, 0), "motion": "surface"}),
                    "xmax": Section({"type": "wall", "restitution": None, "friction": None, "rolling_friction": 0.1,
                                     "velocity": (0, 0, 0), "angular_velocity": (0, 0, 1.0),
                                     "center": (0.5, 0.5, 0.5), "motion": "rigid"})},
        collisions=Section({"restitution": 0.7, "friction": 0.4, "rolling_friction": 0.0}),
        deposition=Section({"zones": ("zmax",)}))
    walls = build_walls(case, FakeMesh())
    names = [walls.names[b] for b in walls.boundary]
    assert "xmin" not in names and len(walls) == 10
    zmin = walls.boundary == 4
    assert np.all(walls.restitution[zmin] == 0.2) and np.all(walls.friction[zmin] == 0.4)
    assert np.all(walls.velocity[zmin] == [1, 0, 0]) and not walls.rigid[zmin].any()
    xmax = walls.boundary == 1
    assert walls.rigid[xmax].all() and np.all(walls.rolling_friction[xmax] == 0.1)
    assert np.all(walls.restitution[xmax] == 0.7)
    assert walls.deposition[walls.boundary == 5].all() and walls.deposition.sum() == 2
    settings = collision_settings(case)
    assert settings.restitution == 0.7 and settings.rest_speed == pytest.approx(3 * G * 1e-3)
    assert (settings.dense_sweeps, settings.gather_contacts) == (20, 4096)   # (keys absent: the defaults)
    tuned = collision_settings(fake_case(collisions=Section({"restitution": 0.7, "friction": 0.4,
                                                              "rolling_friction": 0.0, "dense_sweeps": 45,
                                                              "gather_contacts": 0})))
    assert (tuned.dense_sweeps, tuned.gather_contacts) == (45, 0)
    defaults = build_walls(fake_case(), FakeMesh())
    assert len(defaults) == 12 and np.all(defaults.restitution == 0.9) and np.all(defaults.friction == 0.3)
    open_box = fake_case(boundaries={name: Section({"type": "outlet"}) for name in FakeMesh.boundary_names})
    none = build_walls(open_box, FakeMesh())
    assert len(none) == 0
    state = particles([[0.5, 0.5, 0.5]], [[1.0, 0, 0]])
    advance_with_collisions(state, none, 0.1, settings)
    assert state.x[0, 0] == pytest.approx(0.6)


def test_closest_points():
    """Closest points on a triangle from the face, edge and vertex regions."""
    a, b, c = np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0])
    p = np.array([[0.2, 0.2, 1.0], [2.0, -1.0, 0.5], [1.0, 1.0, 0.0], [0.5, -1.0, 0.0]])
    q, face = closest_points_on_triangles(p, *(np.broadcast_to(v, p.shape) for v in (a, b, c)))
    assert np.allclose(q, [[0.2, 0.2, 0], [1, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0]])
    assert face.tolist() == [True, False, False, False]


def new_particles(x, radius):
    x = np.array(x, float)
    n = len(x)
    return NewParticles(x, np.zeros((n, 3)), np.zeros((n, 3)), np.full(n, radius), np.full(n, 1000.0),
                        np.zeros(n, np.int8))


def test_check_initial_particles():
    """One-line CaseErrors naming the case file and the particle; a good set passes."""
    case, walls = fake_case(), build_walls(fake_case(), FakeMesh())
    good = new_particles([[0.5, 0.5, 0.5], [0.6, 0.5, 0.5]], 0.05)
    check_initial_particles(case, good, np.ones(2, bool), walls)
    with pytest.raises(CaseError, match=r"^case.toml: particle 1: .*outside the domain"):
        check_initial_particles(case, good, np.array([True, False]), walls)
    with pytest.raises(CaseError, match=r"^case.toml: particle 2 .*overlaps particle 0"):
        check_initial_particles(case, new_particles([[0.5, 0.5, 0.5], [0.2, 0.2, 0.2], [0.55, 0.5, 0.5]], 0.05),
                                np.ones(3, bool), walls)
    with pytest.raises(CaseError, match=r"^case.toml: particle 0: .*from a wall"):
        check_initial_particles(case, new_particles([[0.5, 0.5, 0.03]], 0.05), np.ones(1, bool), walls)
    check_initial_particles(case, new_particles([[0.5, 0.5, 0.03]], 0.05), np.ones(1, bool), None)


def test_overlaps_existing():
    """New particles overlapping a present one or an earlier new one are flagged (later loses)."""
    state = particles([[0, 0, 0]], radius=0.01)
    new = new_particles([[0.015, 0, 0], [0.5, 0, 0], [0.51, 0, 0], [0.9, 0, 0]], 0.01)
    assert overlaps_existing(state, new).tolist() == [True, False, True, False]
    assert overlaps_existing(ParticleState.empty(), new).tolist() == [False, False, True, False]


# -- the engine's guarantees (docs/collisions.md) ----------------------------------------------
def pyramid_bed(r, layers_of=6):
    """A square layer of layers_of² touching spheres on the floor, the next layer in its pockets,
    a third in the pockets of that: a packing in static equilibrium (the box closes it in)."""
    grid = r + 2 * r * np.arange(layers_of)
    pocket = 2 * r + 2 * r * np.arange(layers_of - 1)
    h = r * np.sqrt(2)
    x = ([[a, b, r] for a in grid for b in grid] + [[a, b, r + h] for a in pocket for b in pocket]
         + [[a, b, r + 2 * h] for a in grid[1:-1] for b in grid[1:-1]])
    return np.array(x), 2 * r * layers_of


@pytest.mark.mpi
@pytest.mark.parametrize("dense_contacts", [256, 0])
def test_settled_bed_stays_at_rest(dense_contacts):
    """A bed in static equilibrium under gravity for 300 steps, solved as dense steps (256) or by
    resting solves (0): no sphere moves faster than 1e-6 g dt, none spins about the vertical
    faster than 1e-6 g dt / r, and none moves by 1e-6 d (the previous engine: g dt spikes and
    spins of a few rad/s)."""
    r, dt = 0.01, 1e-3
    x, side = pyramid_bed(r)
    state = particles(x, radius=r)
    walls = box(side, 0.5, restitution=0.5, friction=0.5)
    settings = CollisionSettings(restitution=0.5, friction=0.5, rest_speed=3 * G * dt, dense_contacts=dense_contacts)
    loop = TimeLoop(walls, dt, settings)
    speed = spin = 0.0
    for _ in range(300):
        stats = loop.step(state)
        assert stats["dense_steps"] == (dense_contacts > 0) and not stats["capped"]
        speed = max(speed, np.abs(state.v).max())
        spin = max(spin, np.abs(state.omega[:, 2]).max())
    assert speed < 1e-6 * G * dt
    assert spin < 1e-6 * G * dt / r
    assert np.abs(state.x - x).max() < 1e-6 * 2 * r


@pytest.mark.mpi
def test_overlapping_release_is_separated_without_energy():
    """Spheres released overlapping each other and the walls (up to 60 % of a radius), at rest,
    without gravity: after one step no overlap is left beyond 1e-9 of the contact distance, and
    no velocity has appeared (kinetic energy exactly 0): overlaps are removed by moving
    positions, never by velocities."""
    r = 0.01
    rng = np.random.default_rng(5)
    x = rng.uniform(0.4 * r, 0.1 - 0.4 * r, (40, 3))
    x[:, 2] = rng.uniform(0.4 * r, 0.05, 40)
    state = particles(x, radius=r)
    walls = box(0.1, 0.5, restitution=0.5, friction=0.5)
    loop = TimeLoop(walls, 1e-3, CollisionSettings(restitution=0.5, friction=0.5, rest_speed=3 * G * 1e-3),
                    gravity=(0.0, 0.0, 0.0))
    pairs = np.linalg.norm(x[:, None] - x[None], axis=2) + np.eye(len(x))
    assert pairs.min() < 1.2 * r and min(x[:, :2].min(), x[:, 2].min()) < 0.5 * r  # deep overlaps
    for step in range(20):
        stats = loop.step(state)
        pairs = np.linalg.norm(state.x[:, None] - state.x[None], axis=2) + np.eye(len(x))
        inside = min(state.x[:, :2].min(), (0.1 - state.x[:, :2]).min(), state.x[:, 2].min())
        assert np.all(state.v == 0) and np.all(state.omega == 0)
        if pairs.min() >= 2 * r * (1 - 1e-9) and inside >= r * (1 - 1e-9):
            break
    assert step == 0 and stats["overlaps_removed"] > 0


@pytest.mark.mpi
def test_sphere_released_cutting_a_wall():
    """A sphere released with its centre 0.4 r from a side wall, sliding along it at 0.1 m/s
    under gravity on the floor: after one step it is r from the wall, on the floor, slowed only by
    the floor's friction (μ g dt: the overlap made no normal force on the wall, so no friction
    there either) and nothing pushes it off the wall (no energy from the overlap)."""
    r, dt = 0.01, 1e-3
    walls = box(0.1, 0.5, restitution=0.5, friction=0.5)
    state = particles([[0.05, 0.4 * r, r]], [[0.1, 0.0, 0.0]], radius=r)
    loop = TimeLoop(walls, dt, CollisionSettings(restitution=0.5, friction=0.5, rest_speed=3 * G * dt))
    loop.step(state)
    assert state.x[0, 1] == pytest.approx(r, rel=1e-9)
    assert state.v[0, 1] == 0.0 and abs(state.v[0, 2]) < 1e-15
    assert state.v[0, 0] == pytest.approx(0.1 - 0.5 * G * dt, rel=1e-12)
    assert state.x[0, 2] == pytest.approx(r, rel=1e-12)
    for _ in range(100):
        loop.step(state)
        assert abs(state.x[0, 1] - r) < 1e-9 * r and state.v[0, 1] <= 0.0


@pytest.mark.mpi
def test_contact_memory_round_trip_gives_the_same_next_step(tmp_path):
    """The contact memory written as arrays (as to a checkpoint) and read back gives the same next
    step to the bit; without it, the step is not the same (so the memory is used)."""
    r, dt = 0.01, 1e-3
    x, side = pyramid_bed(r, 4)
    rng = np.random.default_rng(2)
    state = particles(x + rng.uniform(-0.05 * r, 0.05 * r, x.shape) + [0, 0, 0.1 * r], radius=r)
    walls = box(side, 0.5, restitution=0.5, friction=0.5)
    settings = CollisionSettings(restitution=0.5, friction=0.5, rest_speed=3 * G * dt)
    loop = TimeLoop(walls, dt, settings)
    for _ in range(60):
        loop.step(state)
    memory = loop.memory
    assert len(memory) > 20 and memory.normal_impulse.min() > 0
    np.savez(tmp_path / "memory.npz", **memory.to_arrays())
    with np.load(tmp_path / "memory.npz") as stored:
        restored = ContactMemory.from_arrays(dict(stored))
    after = []
    for remembered in (memory, restored, None):
        copy = particles(state.x, state.v, radius=r, omega=state.omega)
        copy.v[copy.movable] += np.array([0, 0, -G]) * dt
        result = advance_with_collisions(copy, walls, dt, settings, remembered)
        after.append((copy, result.memory))
    (a, memory_a), (b, memory_b), (c, _) = after
    for name in ("x", "v", "omega"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    for name, value in memory_a.to_arrays().items():
        assert np.array_equal(value, memory_b.to_arrays()[name])
    assert not np.array_equal(c.v, a.v)


@pytest.mark.mpi
def test_rigid_walls_move_in_the_result_not_in_place():
    """A moving rigid wall: the step returns the moved walls (V dt further) and leaves the walls
    it was given as they were; a surface-moving wall is returned as it is."""
    paddle = rectangle((0, -0.5, -0.5), (0, 1, 0), (0, 0, 1), velocity=(2.0, 0, 0), rigid=True)
    before = paddle.a.copy()
    result = advance_with_collisions(particles([[0.5, 0, 0]]), paddle, 0.01, CollisionSettings())
    assert np.array_equal(paddle.a, before)
    assert np.allclose(result.walls.a - before, [0.02, 0, 0], rtol=0, atol=1e-15)
    belt = floor(velocity=(1.0, 0, 0))
    assert advance_with_collisions(particles([[0, 0, 0.5]]), belt, 0.01, CollisionSettings()).walls is belt


@pytest.mark.mpi
def test_dense_steps_never_gain_kinetic_energy():
    """A dense gas of elastic, frictional spheres in a closed box without gravity, every step a
    dense step (all contacts at once, Newton's restitution e = 1): the kinetic energy never grows
    by more than 1e-12 of itself in a step."""
    r = 0.005
    rng = np.random.default_rng(11)
    g = np.arange(r * 1.05, 0.05 - r, 2.1 * r)
    x = np.array([[a, b, c] for a in g for b in g for c in g])
    state = particles(x, rng.normal(0, 0.5, x.shape), radius=r, omega=rng.normal(0, 50, x.shape))
    walls = box(0.05, 0.05, restitution=1.0, friction=0.5)
    top = rectangle((0, 0, 0.05), (0, 0.05, 0), (0.05, 0, 0), restitution=1.0, friction=0.5)
    walls = Walls(*(np.concatenate([getattr(w, f) for w in (walls, top)]) for f in (
        "a", "b", "c", "normal", "boundary", "restitution", "friction", "rolling_friction", "velocity",
        "angular_velocity", "center", "rigid", "deposition")))
    settings = CollisionSettings(restitution=1.0, friction=0.5, rest_speed=1e-3, dense_contacts=1)
    loop = TimeLoop(walls, 1e-3, settings, gravity=(0.0, 0.0, 0.0))
    energy = kinetic(state)
    for _ in range(100):
        stats = loop.step(state)
        assert stats["dense_steps"] == 1
        now = kinetic(state)
        assert now <= energy * (1 + 1e-12)
        energy = now


def test_wall_search_matches_the_direct_test():
    """The walls' grid search lists exactly the (point, triangle) pairs whose boxes and bounding
    spheres meet (a direct test over every pair), in order, for triangles of very different sizes;
    every triangle within reach of a point is among them."""
    rng = np.random.default_rng(8)
    corners = rng.uniform(0, 1, (300, 1, 3)) + rng.uniform(-1, 1, (300, 3, 3)) * rng.uniform(0.001, 0.2, (300, 1, 1))
    walls = Walls.from_triangles(corners)
    points = rng.uniform(-0.1, 1.1, (500, 3))
    reach = rng.uniform(0, 0.05, 500)
    extra = rng.uniform(0, 0.02, 300)
    p, k = walls.near(points, reach, extra)
    grow = reach[:, None, None] + extra[None, :, None]
    low, high = np.min(corners, axis=1), np.max(corners, axis=1)
    boxes = np.all((low[None] - grow <= points[:, None]) & (points[:, None] <= high[None] + grow), axis=2)
    distance = np.linalg.norm(points[:, None] - walls.centroid[None], axis=2)
    direct = np.argwhere(boxes & (distance <= reach[:, None] + walls.bounding_radius[None] + extra[None]))
    assert len(direct) > 300
    assert np.array_equal(np.column_stack([p, k]), direct)
    a, b, c = (np.repeat(corners[None, :, i], len(points), 0).reshape(-1, 3) for i in range(3))
    q, _ = closest_points_on_triangles(np.repeat(points, len(corners), 0), a, b, c)
    within = np.argwhere(np.linalg.norm(np.repeat(points, len(corners), 0) - q, axis=1).reshape(len(points), -1)
                         <= reach[:, None])
    assert set(map(tuple, within)) <= set(map(tuple, direct)) and len(within) > 50


@pytest.mark.parametrize("spread", [0.1, 100.0])
def test_pair_search_matches_the_direct_test(spread):
    """The cell list lists exactly the pairs closer than r_i + r_j (+ 1e-6) + reach, i < j, sorted:
    for a pack, and for a cluster in a domain so wide that the cells are grown; also with only
    some particles chosen."""
    from pmpm.collisions.jit import kernels
    from pmpm.collisions.search import candidate_pairs
    rng = np.random.default_rng(4)
    x = rng.uniform(0, 0.1, (600, 3))
    x[:100] = rng.uniform(0, spread, (100, 3))
    radius, reach = rng.uniform(0.002, 0.006, 600), 0.003
    distance = np.linalg.norm(x[:, None] - x[None], axis=2)
    close = np.triu(distance <= (radius[:, None] + radius[None]) * (1 + 1e-6) + reach, 1)
    assert np.array_equal(candidate_pairs(x, radius, reach, kernels().cell_list), np.argwhere(close))
    around = rng.choice(600, 50, replace=False)
    chosen = np.zeros(600, bool)
    chosen[around] = True
    expected = np.argwhere(close & (chosen[:, None] | chosen[None]))
    assert len(expected) > 10
    assert np.array_equal(candidate_pairs(x, radius, reach, kernels().cell_list, around), expected)
    # each particle with its own reach (its travel in a step): r_i + r_j (+ 1e-6) + reach_i + reach_j
    each = rng.uniform(0.0, 0.003, 600) * (rng.random(600) < 0.1)
    close = np.triu(distance <= (radius[:, None] + radius[None]) * (1 + 1e-6) + each[:, None] + each[None], 1)
    assert np.array_equal(candidate_pairs(x, radius, each, kernels().cell_list), np.argwhere(close))
    # a slow pack with a few particles forty times as fast (they search many cells around them)
    each = np.full(600, 2e-4)
    each[rng.choice(600, 5, replace=False)] = 8e-3
    close = np.triu(distance <= (radius[:, None] + radius[None]) * (1 + 1e-6) + each[:, None] + each[None], 1)
    assert np.array_equal(candidate_pairs(x, radius, each, kernels().cell_list), np.argwhere(close))
    expected = np.argwhere(close & (chosen[:, None] | chosen[None]))
    assert np.array_equal(candidate_pairs(x, radius, each, kernels().cell_list, around), expected)


def test_a_dense_step_finds_its_contacts_by_each_particle_s_travel():
    """The dense step's contacts are searched by each particle's own travel, not by the reach of
    the fastest: the same contacts, with the same gaps, normals and times, as the search by reach.
    A step not expected to be dense (``dense_likely=False``: searched by reach at once) takes the
    same decision and the same record, dense or not."""
    from pmpm.collisions.jit import kernels
    from pmpm.collisions.search import find_contacts
    from pmpm.collisions.solver import Bodies
    rng = np.random.default_rng(8)
    centres = np.stack(np.meshgrid(*[np.arange(8) * 0.01005] * 3, indexing="ij"), -1).reshape(-1, 3)
    particles = ParticleState.empty().appended(np.arange(len(centres)), centres, rng.normal(0, 0.05, centres.shape),
                                               np.zeros_like(centres), np.full(len(centres), 0.005),
                                               np.full(len(centres), 2500.0), np.zeros(len(centres), np.int8))
    particles.v[0] = [3.0, 0.0, 0.0]    # one fast particle sets the reach for everyone
    bodies, dt = Bodies.of(particles), 1e-3
    reach = 2.0 * 1.25 * 3.0 * dt
    by_travel, dense, acting = find_contacts(bodies, None, dt, reach, 0.9, 0.3, kernels(), dense_contacts=10)
    by_reach, _, acting_by_reach = find_contacts(bodies, None, dt, reach, 0.9, 0.3, kernels(), dense_contacts=10 ** 9)
    assert dense and acting == acting_by_reach > 100
    can_act = (by_reach.gap <= np.linalg.norm(bodies.v[by_reach.first] - bodies.v[by_reach.second], axis=1) * dt
               + 1e-6 * 0.005)
    assert len(by_reach) > len(by_travel) and np.count_nonzero(can_act) == len(by_travel)
    for name in ("first", "second", "gap", "normal", "time"):
        assert np.array_equal(getattr(by_travel, name), getattr(by_reach, name)[can_act]), name
    for dense_contacts, expected in ((10, by_travel), (10 ** 9, by_reach)):
        at_once, dense_at_once, acting_at_once = find_contacts(bodies, None, dt, reach, 0.9, 0.3, kernels(),
                                                               dense_contacts=dense_contacts, dense_likely=False)
        assert dense_at_once == (dense_contacts == 10) and acting_at_once == acting
        for name in ("first", "second", "gap", "normal", "time"):
            assert np.array_equal(getattr(at_once, name), getattr(expected, name)), name


@pytest.mark.mpi
def test_dense_impact_under_a_load_stays_above_the_floor():
    """A column of 20 touching spheres falling at 2 m/s onto a floor 1 mm below it, as a dense
    step: the impact inside the step moves the bottom sphere back by its own velocity change
    times the impulse-weighted contact time, so it ends above the floor and the column is not
    squeezed into it (by the floor impulse, which carries the whole column's momentum, it would
    end 38 mm back, through the floor)."""
    r, gap, u, dt = 0.005, 1e-3, 2.0, 1e-3
    state = particles([[0, 0, r + gap + 2 * r * k] for k in range(20)], [[0, 0, -u]] * 20, radius=r)
    settings = CollisionSettings(restitution=0.5, friction=0.3, rest_speed=0.01, dense_contacts=1)
    stats = advance_with_collisions(state, floor(restitution=0.5, friction=0.3), dt, settings).stats
    assert stats["dense_steps"] == 1 and stats["wall_collisions"] == 1
    assert r * (1 - 1e-6) <= state.x[0, 2] <= r + gap + u * dt
    assert np.diff(state.x[:, 2]).min() >= 2 * r * (1 - 1e-6)
    assert np.all(state.v[:, 2] > -u)  # every sphere slowed by the impact


def test_contact_memory_reads_the_arrays_of_the_engine_before():
    """A checkpoint written by the engine before holds keys first · 2^31 + other + 2^30 and the
    tangential impulse on the contact's i with a sign: read back, the same contacts and the
    impulses on the lower id (a pair stored the other way round turns its tangential impulse)."""
    keys = np.array([3 * 2 ** 31 + 7 + 2 ** 30, 5 * 2 ** 31 + (-1 - 2) + 2 ** 30])
    memory = ContactMemory.from_arrays({"keys": keys, "normal": np.array([1.0, 2.0]),
                                        "tangential": np.array([[1.0, 0, 0], [0, 1.0, 0]]), "sign": np.array([-1.0, 1.0])})
    assert memory.first_id.tolist() == [3, 5] and memory.second_id.tolist() == [7, -3]
    assert memory.normal_impulse.tolist() == [1.0, 2.0]
    assert memory.tangential_impulse.tolist() == [[-1.0, 0, 0], [0, 1.0, 0]]
    assert np.all(np.diff(memory.keys) > 0)


def test_the_wall_search_finds_the_triangles_on_its_grids_upper_faces():
    """The pool table's floor and far cushion in 2 cm squares (the faces of a 127 × 64 × 13-cell
    box): the search grid is capped at 64 cells along x, so the triangles on x = 2.54 m lie on the
    grid's upper face, whose index came out one past the last cell. They were in no cell, and a
    ball rolling at 2 m/s passed through that wall. Now a point 2 cm from it finds them all."""
    def squares(corner, edge_u, edge_v, nu, nv):
        i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
        a = corner + (i.ravel()[:, None] * edge_u + j.ravel()[:, None] * edge_v)
        b, c, d = a + edge_u, a + edge_u + edge_v, a + edge_v
        return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    floor = squares(np.zeros(3), np.array([2.54 / 127, 0, 0]), np.array([0, 1.27 / 64, 0]), 127, 64)
    cushion = squares(np.array([2.54, 0, 0]), np.array([0, 1.27 / 64, 0]), np.array([0, 0, 0.26 / 13]), 64, 13)
    walls = Walls.from_triangles(np.concatenate([floor, cushion]), boundary=np.repeat([0, 1], [len(floor), len(cushion)]))
    assert walls.grid(0.03)[2][0] == 64
    point = np.array([[2.52, 0.95, 0.028575]])
    _, found = walls.near(point, 0.03)
    closest, _ = closest_points_on_triangles(np.repeat(point, len(walls), axis=0), walls.a, walls.b, walls.c)
    within = np.flatnonzero(np.linalg.norm(closest - point, axis=1) <= 0.03)
    assert (walls.boundary[within] == 1).sum() > 4 and set(within) <= set(found)
