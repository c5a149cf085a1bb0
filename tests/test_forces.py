"""Gravity with buoyancy and the field forces of paper eq. 9-10, against their closed forms."""
import numpy as np
import pytest

from pmpm.case import Section
from pmpm.collisions import CollisionSettings, Walls, advance_with_collisions
from pmpm.forces import field_forces, field_forces_of_case, gravity_buoyancy
from pmpm.particles import ParticleState, accelerate


def particles(x, radius=0.01, density=1000.0, v=None) -> ParticleState:
    x = np.array(x, float).reshape(-1, 3)
    n = len(x)
    return ParticleState.empty().appended(np.arange(n), x, np.zeros((n, 3)) if v is None else np.array(v, float),
                                          np.zeros((n, 3)), np.broadcast_to(np.asarray(radius, float), n).copy(),
                                          np.broadcast_to(np.asarray(density, float), n).copy(), np.zeros(n, np.int8))


def box_floor_and_wall() -> Walls:
    """Floor z = 0 (boundary 0) and side wall x = 0 (boundary 1), two triangles each."""
    floor = [[[0, -1, 0], [1, -1, 0], [1, 1, 0]], [[0, -1, 0], [1, 1, 0], [0, 1, 0]]]
    side = [[[0, -1, 0], [0, 1, 1], [0, 1, 0]], [[0, -1, 0], [0, -1, 1], [0, 1, 1]]]
    return Walls.from_triangles(floor + side, normal=[[0, 0, 1]] * 2 + [[1, 0, 0]] * 2, boundary=[0, 0, 1, 1])


def test_gravity_with_buoyancy():
    """(ρ_p − ρ_f) V g per particle, exactly; a particle lighter than the fluid rises."""
    state = particles([[0, 0, 0], [1, 0, 0]], radius=[0.01, 0.02], density=[2500.0, 500.0])
    g = np.array([0.0, 0.0, -9.81])
    force = gravity_buoyancy(state, g, 1000.0)
    volume = 4 / 3 * np.pi * np.array([0.01, 0.02]) ** 3
    assert np.allclose(force, (np.array([1500.0, -500.0]) * volume)[:, None] * g, rtol=1e-14, atol=0)
    assert force[1, 2] > 0
    assert np.allclose(gravity_buoyancy(state, g, 0.0)[:, 2], state.mass * g[2], rtol=1e-14)


@pytest.mark.parametrize("G_p", [2.0, -2.0])
def test_pair_force_law(G_p):
    """Eq. 9 for two unequal particles: |F| = G_p M_1^n1 M_2^n2 / R^n3 along the line of centres,
    attracting for G_p > 0, and F_2 = −F_1 exactly."""
    state = particles([[0, 0, 0], [0.03, 0.04, 0]], radius=[0.01, 0.015], density=[1000.0, 3000.0])
    n1, n2, n3 = 1.0, 0.5, 2.5
    force = field_forces(state, None, G_p, n1, n2, n3, 0.0, 1.0, 2.0, cutoff=1.0)
    m1, m2 = state.mass
    size = G_p * m1 ** n1 * m2 ** n2 / 0.05 ** n3
    towards_2 = np.array([0.6, 0.8, 0.0])
    assert np.allclose(force[0], size * towards_2, rtol=1e-13, atol=0)
    assert np.all(force[1] == -force[0])
    assert (force[0] @ towards_2 > 0) == (G_p > 0)


def test_many_pairs_match_direct_sum_and_conserve_momentum():
    """60 random particles: the k-d tree sum equals the direct double sum over pairs within the
    cutoff (1e-12 relative), and the forces add up to zero (to round-off)."""
    rng = np.random.default_rng(3)
    state = particles(rng.uniform(0, 0.3, (60, 3)), radius=rng.uniform(0.005, 0.01, 60))
    G_p, n1, n2, n3, cutoff = 1e-3, 1.0, 1.0, 2.0, 0.1
    force = field_forces(state, None, G_p, n1, n2, n3, 0.0, 1.0, 2.0, cutoff)
    m = state.mass
    direct = np.zeros((60, 3))
    for i in range(60):
        for j in range(60):
            d = state.x[j] - state.x[i]
            R = np.linalg.norm(d)
            if i != j and R <= cutoff:
                direct[i] += G_p * m[i] ** n1 * m[j] ** n2 / R ** n3 * d / R
    assert np.allclose(force, direct, rtol=1e-12, atol=1e-12 * np.abs(direct).max())
    assert np.abs(force.sum(0)).max() < 1e-13 * np.abs(force).max()


def test_wall_force_law():
    """Eq. 10: one term per wall boundary, G_w M^n4 / R^n5 towards the wall (G_w > 0); a particle
    over the floor's shared diagonal still feels the floor once; out of the cutoff, nothing."""
    walls = box_floor_and_wall()
    state = particles([[0.5, 0.5, 0.1], [0.05, 0.0, 0.5], [0.5, 0.0, 0.8]])
    G_w, n4, n5 = 3.0, 1.0, 2.0
    force = field_forces(state, walls, 0.0, 1.0, 1.0, 2.0, G_w, n4, n5, cutoff=0.2)
    m = state.mass
    assert np.allclose(force[0], [0, 0, -G_w * m[0] ** n4 / 0.1 ** n5], rtol=1e-13)  # on the diagonal
    assert np.allclose(force[1], [-G_w * m[1] ** n4 / 0.05 ** n5, 0, 0], rtol=1e-13)
    assert np.all(force[2] == 0)
    repel = field_forces(state, walls, 0.0, 1.0, 1.0, 2.0, -G_w, n4, n5, cutoff=0.2)
    assert np.allclose(repel, -force)


def test_default_cutoff_is_five_mean_diameters():
    """[field_forces] without cutoff: pairs closer than 5 mean diameters (0.1 m here) interact."""
    section = Section({"G_p": 1.0, "n1": 1.0, "n2": 1.0, "n3": 2.0, "G_w": 0.0, "n4": 1.0, "n5": 2.0,
                       "cutoff": None})
    near = field_forces_of_case(particles([[0, 0, 0], [0.09, 0, 0]]), None, section)
    far = field_forces_of_case(particles([[0, 0, 0], [0.11, 0, 0]]), None, section)
    assert near[0, 0] > 0 and np.all(far == 0)


def test_two_attracting_particles_in_time():
    """Two particles released at rest under eq. 9 attraction (n3 = 2, like gravity): the
    separation follows R'' = −G (m1 + m2) / R² (RK-free check: R(t) ≈ R0 − ½ a0 t² early on)
    and the total momentum stays zero while they fall together and collide."""
    state = particles([[0, 0, 0], [0.1, 0, 0]], radius=[0.01, 0.012], density=[1000.0, 2000.0])
    G_p, dt = 5.0, 1e-4
    m1, m2 = state.mass
    a0 = G_p * (m1 + m2) / 0.1 ** 2
    settings = CollisionSettings(restitution=0.5, friction=0.3)
    for step in range(1, 3001):
        force = field_forces(state, None, G_p, 1.0, 1.0, 2.0, 0.0, 1.0, 2.0, cutoff=1.0)
        accelerate(state, force, np.zeros_like(force), dt)
        advance_with_collisions(state, None, dt, settings)
        if step == 200:
            t = step * dt
            assert np.linalg.norm(state.x[1] - state.x[0]) == pytest.approx(0.1 - 0.5 * a0 * t * t, rel=1e-3)
        assert np.abs(state.mass @ state.v).max() < 1e-15
    assert np.linalg.norm(state.x[1] - state.x[0]) >= 0.022 * (1 - 1e-9)
