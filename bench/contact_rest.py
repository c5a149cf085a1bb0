"""How a contact engine treats rest and overlaps, on whichever ``pmpm`` is imported (run by
``bench/contacts.py`` on this checkout and, with ``--baseline``, on another; it works with the
engine before and after ``advance_with_collisions`` returned a ``ContactStep``):

1. a bed in static equilibrium (a 6 × 6 square layer, a layer in its pockets, a third on top, in
   a box), 1000 steps under gravity: the largest speed and spin about the vertical in the last
   500 steps, and the kinetic energy at the end;
2. 200 spheres poured at random into a box, 3 s under gravity: the same over the last second;
3. a sphere released 0.4 r from a wall (overlapping it by 0.6 r), at rest, without gravity: its
   speed after one step and the wall time of that step.

    .venv/bin/python bench/contact_rest.py
"""
from __future__ import annotations

import inspect
import time

import numpy as np

from pmpm.collisions import CollisionSettings, Walls, advance_with_collisions
from pmpm.particles import ParticleState

G = 9.81


def spheres(x, v, r):
    n = len(x)
    args = (np.arange(n), x, v, np.zeros((n, 3)), np.full(n, r), np.full(n, 2500.0), np.zeros(n, np.int8))
    empty = ParticleState.empty()
    if hasattr(empty, "appended"):
        return empty.appended(*args)
    empty.append(*args)
    return empty


def box(side, height):
    o = np.zeros(3)
    faces = [(o, (side, 0, 0), (0, side, 0)), (o, (0, 0, height), (side, 0, 0)),
             ((0, side, 0), (side, 0, 0), (0, 0, height)), (o, (0, side, 0), (0, 0, height)),
             ((side, 0, 0), (0, 0, height), (0, side, 0))]
    triangles = []
    for origin, e1, e2 in faces:
        p, e1, e2 = np.asarray(origin, float), np.asarray(e1, float), np.asarray(e2, float)
        triangles += [[p, p + e1, p + e1 + e2], [p, p + e1 + e2, p + e2]]
    return Walls.from_triangles(triangles, restitution=0.5, friction=0.5)


class Loop:
    """Gravity, then the contacts, carrying the contact memory and the walls if the engine has them."""

    def __init__(self, walls, dt, gravity=(0.0, 0.0, -G)):
        self.walls, self.dt, self.gravity, self.memory = walls, dt, np.asarray(gravity), None
        self.settings = CollisionSettings(restitution=0.5, friction=0.5, rest_speed=3 * G * dt)
        self.carries = "memory" in inspect.signature(advance_with_collisions).parameters

    def step(self, state):
        state.v[state.movable] += self.gravity * self.dt
        if self.carries:
            result = advance_with_collisions(state, self.walls, self.dt, self.settings, self.memory)
            self.walls, self.memory = result.walls, result.memory
        else:  # the engine before: it keeps what it remembers on the state, moves the walls in place
            advance_with_collisions(state, self.walls, self.dt, self.settings)


def kinetic(state):
    return float(0.5 * np.sum(state.mass * np.sum(state.v ** 2, 1))
                 + 0.5 * np.sum(state.inertia * np.sum(state.omega ** 2, 1)))


def watch(state, loop, steps, last):
    speed = spin = 0.0
    for k in range(steps):
        loop.step(state)
        if k >= steps - last:
            speed = max(speed, float(np.abs(state.v).max()))
            spin = max(spin, float(np.abs(state.omega[:, 2]).max()))
    return speed, spin, kinetic(state)


def main():
    r, dt = 0.01, 1e-3
    grid, pocket, h = r + 2 * r * np.arange(6), 2 * r + 2 * r * np.arange(5), r * np.sqrt(2)
    x = np.array([[a, b, r] for a in grid for b in grid] + [[a, b, r + h] for a in pocket for b in pocket]
                 + [[a, b, r + 2 * h] for a in grid[1:-1] for b in grid[1:-1]])
    speed, spin, energy = watch(spheres(x, np.zeros_like(x), r), Loop(box(12 * r, 0.5), dt), 1000, 500)
    print(f"  bed in equilibrium (77 spheres), last 500 of 1000 steps: max speed {speed:.2e} m/s "
          f"(g dt = {G * dt:.2e}), max spin about the vertical {spin:.2e} rad/s, kinetic energy {energy:.1e} J")
    rng = np.random.default_rng(1)
    r, side, points = 0.005, 0.08, []
    while len(points) < 200:
        p = rng.uniform([r, r, r], [side - r, side - r, 0.4])
        if all(np.linalg.norm(p - q) > 2.05 * r for q in points):
            points.append(p)
    state = spheres(np.array(points), rng.normal(0, 0.1, (200, 3)), r)
    speed, spin, energy = watch(state, Loop(box(side, 0.5), dt), 3000, 1000)
    print(f"  200 spheres poured, last 1 of 3 s: max speed {speed:.2e} m/s, max spin about the vertical "
          f"{spin:.2e} rad/s, kinetic energy {energy:.1e} J")
    state = spheres(np.array([[0.05, 0.4 * r, 0.05]]), np.zeros((1, 3)), r)
    loop = Loop(box(0.1, 0.5), dt, gravity=(0.0, 0.0, 0.0))
    start = time.perf_counter()
    loop.step(state)
    seconds = time.perf_counter() - start
    print(f"  sphere released 0.6 r into a wall, at rest: speed after one step {np.linalg.norm(state.v[0]):.3g} m/s, "
          f"distance to the wall {state.x[0, 1] / r:.3f} r, the step took {seconds:.3f} s")


if __name__ == "__main__":
    main()
