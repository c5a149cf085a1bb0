"""The particles' state: arrays sorted by global id; on several ranks, the particles a rank owns
(ARCHITECTURE.md, "Particles"). Solid spheres: m = ρ 4/3 π r³, I = 2/5 m r².

A ``ParticleState`` is a value: the stages of a time step return a new one (``appended``,
``without``, or a ``copy`` they then change), so the state a step started from stays as it was
(the time loop keeps it, to write it if the step fails).
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np
from numba import njit

FREE, FIXED, PRESCRIBED = 0, 1, 2  # ParticleState.motion codes (pmpm.injection.MOTION_CODES)


@dataclass(frozen=True)
class ParticleState:
    """Every particle's state (SI). Rows are particles, sorted by ``id``."""

    id: np.ndarray        # (n,) int64, never reused
    x: np.ndarray         # (n, 3) centre position
    v: np.ndarray         # (n, 3) translational velocity
    omega: np.ndarray     # (n, 3) angular velocity
    radius: np.ndarray    # (n,)
    density: np.ndarray   # (n,)
    motion: np.ndarray    # (n,) int8: FREE, FIXED or PRESCRIBED
    deposited: np.ndarray  # (n,) bool: stuck to a deposition wall or to a deposited particle

    @classmethod
    def empty(cls) -> "ParticleState":
        z3, z1 = np.zeros((0, 3)), np.zeros(0)
        return cls(np.zeros(0, np.int64), z3, z3.copy(), z3.copy(), z1, z1.copy(),
                   np.zeros(0, np.int8), np.zeros(0, bool))

    def __len__(self) -> int:
        return len(self.id)

    @property
    def volume(self) -> np.ndarray:
        return 4.0 / 3.0 * np.pi * self.radius ** 3

    @property
    def mass(self) -> np.ndarray:
        return self.density * self.volume

    @property
    def inertia(self) -> np.ndarray:
        """Moment of inertia of a solid sphere about its centre, 2/5 m r²."""
        return 0.4 * self.mass * self.radius ** 2

    @property
    def movable(self) -> np.ndarray:
        """Particles whose velocities respond to forces and impulses (free and not deposited)."""
        return (self.motion == FREE) & ~self.deposited

    @property
    def moving(self) -> np.ndarray:
        """Particles that move over a step (free or prescribed, not deposited)."""
        return (self.motion != FIXED) & ~self.deposited

    def top_speed(self) -> float:
        """The largest speed (m/s) of a moving particle; 0 without one."""
        return fastest(self.v, self.moving)

    def copy(self) -> "ParticleState":
        """A copy whose arrays may be changed in place without touching this state."""
        return replace(self, **{f.name: getattr(self, f.name).copy() for f in fields(self)})

    def appended(self, ids, x, v, omega, radius, density, motion) -> "ParticleState":
        """These particles and the given ones (ids larger than every id held, so the rows stay sorted)."""
        n = len(ids)
        return ParticleState(
            np.concatenate([self.id, np.asarray(ids, np.int64)]),
            np.concatenate([self.x, np.reshape(x, (n, 3))]),
            np.concatenate([self.v, np.reshape(v, (n, 3))]),
            np.concatenate([self.omega, np.reshape(omega, (n, 3))]),
            np.concatenate([self.radius, radius]),
            np.concatenate([self.density, density]),
            np.concatenate([self.motion, np.asarray(motion, np.int8)]),
            np.concatenate([self.deposited, np.zeros(n, bool)]))

    def without(self, which: np.ndarray) -> "ParticleState":
        """These particles less those where ``which`` (bool mask) is true."""
        keep = ~which
        return replace(self, **{f.name: getattr(self, f.name)[keep] for f in fields(self)})


def accelerate(state: ParticleState, force: np.ndarray, torque: np.ndarray, dt: float) -> None:
    """Newton–Euler update of the free particles' V and ω over dt (explicit), in place."""
    _accelerate(state.v, state.omega, np.ascontiguousarray(force, float), np.ascontiguousarray(torque, float),
                state.mass, state.radius, state.motion, state.deposited, float(dt))


@njit(cache=True)
def _accelerate(v, omega, force, torque, mass, radius, motion, deposited, dt):
    """``accelerate``, compiled (every step, every particle): the movable ones' V += dt F / m and
    ω += dt T / I, I = 0.4 m r² (``ParticleState.inertia``'s operations, in its order)."""
    for i in range(len(mass)):
        if motion[i] == FREE and not deposited[i]:
            inertia = 0.4 * mass[i] * (radius[i] * radius[i])
            for d in range(3):
                v[i, d] += dt * force[i, d] / mass[i]
                omega[i, d] += dt * torque[i, d] / inertia


def fastest(v: np.ndarray, moving: np.ndarray) -> float:
    """The largest speed (m/s) among the velocities ``v`` (n, 3) where ``moving``; 0 where none is."""
    return float(np.sqrt((v[moving] ** 2).sum(1).max())) if moving.any() else 0.0
