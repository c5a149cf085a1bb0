"""The particle state: a value that the stages of a step replace rather than change, and the
Newton–Euler update of free particles."""
import numpy as np
import pytest

from pmpm.particles import FIXED, FREE, PRESCRIBED, ParticleState, accelerate


def three_particles() -> ParticleState:
    return ParticleState.empty().appended(
        np.array([0, 1, 2]), np.arange(9.0).reshape(3, 3), np.ones((3, 3)), np.zeros((3, 3)),
        np.array([0.01, 0.02, 0.03]), np.array([1000.0, 2000.0, 3000.0]), np.array([FREE, FIXED, PRESCRIBED]))


def test_mass_and_moment_of_inertia_of_solid_spheres():
    """m = ρ 4/3 π r³ and I = 2/5 m r², exact to round-off."""
    state = three_particles()
    mass = state.density * 4 / 3 * np.pi * state.radius ** 3
    np.testing.assert_allclose(state.mass, mass, rtol=1e-15)
    np.testing.assert_allclose(state.inertia, 0.4 * mass * state.radius ** 2, rtol=1e-15)
    assert state.movable.tolist() == [True, False, False]


def test_new_states_leave_the_old_one_as_it_was():
    """``appended``, ``without`` and ``copy`` return new states; the arrays of the state they came
    from keep their values (the time loop relies on it to write the last good state)."""
    state = three_particles()
    before = {name: getattr(state, name).copy() for name in ("id", "x", "v", "omega", "radius", "density")}
    more = state.appended(np.array([7]), np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)), np.array([0.05]),
                          np.array([500.0]), np.array([FREE]))
    fewer = state.without(np.array([False, True, False]))
    changed = state.copy()
    changed.x[:] = -1.0
    changed.v[0] = 99.0
    for name, values in before.items():
        np.testing.assert_array_equal(getattr(state, name), values)
    assert more.id.tolist() == [0, 1, 2, 7] and len(more) == 4 and not more.deposited.any()
    assert fewer.id.tolist() == [0, 2] and fewer.radius.tolist() == [0.01, 0.03]
    with pytest.raises(AttributeError):
        state.x = np.zeros((3, 3))


def test_accelerate_moves_free_particles_only():
    """Δv = F dt / m and Δω = T dt / I for the free particle; fixed, prescribed and deposited
    particles keep their velocities."""
    state = three_particles()
    force, torque, dt = np.array([[1.0, -2.0, 3.0]] * 3), np.array([[0.0, 0.5, 0.0]] * 3), 1e-3
    moved = state.copy()
    accelerate(moved, force, torque, dt)
    np.testing.assert_allclose(moved.v[0], 1.0 + force[0] * dt / state.mass[0], rtol=1e-14)
    np.testing.assert_allclose(moved.omega[0], torque[0] * dt / state.inertia[0], rtol=1e-14)
    np.testing.assert_array_equal(moved.v[1:], state.v[1:])
    np.testing.assert_array_equal(moved.omega[1:], state.omega[1:])
    moved.deposited[0] = True
    stuck = moved.copy()
    accelerate(stuck, force, torque, dt)
    np.testing.assert_array_equal(stuck.v, moved.v)
