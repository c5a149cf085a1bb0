"""The particles' side of a coupled step: new velocities from the momentum the forcing exchanged.

Free particles only (fixed and prescribed ones keep their velocities, and their force is the
impulse they took over dt). ``[coupling] update``:

- ``implicit`` (default): particle and fluid are solved together, the particle's inertia raised by
  what the cells it forces hand back when it speeds up (``damped_*``: the penalty; ``blended_change``:
  the paper's patch with θ = min(1, m/M)), so that light particles converge instead of ringing;
- ``explicit``: the paper's update, m ΔV = dt F_ext + impulse; it rings for light particles, so the
  run watches for that (``watch_ringing``) and stops with exit 3 and advice.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import NumericalError
from ..fluid import FluidState
from ..particles import ParticleState
from ..parallel import agree
from .memory import CouplingMemory, by_id


@dataclass(frozen=True)
class External:
    """The forces on each particle that are not the fluid's this step: gravity with buoyancy and
    field forces (n, 3) N, and their torques (n, 3) N m."""

    force: np.ndarray
    torque: np.ndarray


@dataclass(frozen=True)
class Exchange:
    """A coupled step's end: the flow, the hydrodynamic force and torque (n, 3) on each particle
    (N, N m), and the coupling's memory for the next step."""

    fluid: FluidState
    force: np.ndarray
    torque: np.ndarray
    memory: CouplingMemory


def damped_guess(state: ParticleState, external: External, impulse: np.ndarray, dt: float,
                 response: np.ndarray, response_spin: np.ndarray, guess_v: np.ndarray, guess_omega: np.ndarray):
    """The next guess of a forcing pass, particle and fluid solved together:

        (m + M_c) V_next = m Vⁿ + dt F_ext + J + M_c V_guess,   M_c the cells' response (n,),

    ω likewise with ``response_spin``; ``impulse`` (n, 6) J with its moment. Non-free particles keep
    their velocities. Returns (v, omega), each (n, 3)."""
    m, inertia, free = state.mass, state.inertia, state.movable
    v = (m[:, None] * state.v + dt * external.force + impulse[:, :3]
         + response[:, None] * guess_v) / (m + response)[:, None]
    omega = (inertia[:, None] * state.omega + dt * external.torque + impulse[:, 3:]
             + response_spin[:, None] * guess_omega) / (inertia + response_spin)[:, None]
    return np.where(free[:, None], v, state.v), np.where(free[:, None], omega, state.omega)


def damped_change(state: ParticleState, external: External, impulse: np.ndarray, dt: float,
                  damping: np.ndarray, damping_spin: np.ndarray, solved_v: np.ndarray, solved_omega: np.ndarray):
    """The step's velocity changes: m ΔV = dt F_ext + J where ``damping`` is 0 (exact), else the
    damped update of the last guess ``solved_v`` as in ``damped_guess``. Returns (dv, dw)."""
    m, inertia = state.mass, state.inertia
    dv = (dt * external.force + impulse[:, :3] + damping[:, None] * (solved_v - state.v)) / (m + damping)[:, None]
    dw = (dt * external.torque + impulse[:, 3:] + damping_spin[:, None] * (solved_omega - state.omega)
          ) / (inertia + damping_spin)[:, None]
    return dv, dw


def blended_change(state: ParticleState, external: External, impulse: np.ndarray, dt: float,
                   covered: np.ndarray, moment: np.ndarray, explicit: bool):
    """The paper's patch: (m + (1 − θ) M) ΔV = dt F_ext + J, θ = min(1, m/M) with M the covered
    fluid mass (n,) (``explicit``: θ = 1, the paper's update); ω likewise with the covered moment
    of inertia. On a coarse mesh M can be several times ρf V, so M, not ρf V, decides. Returns (dv, dw)."""
    m, inertia, n = state.mass, state.inertia, len(state)
    tiny = np.finfo(float).tiny
    theta = np.ones(n) if explicit else np.minimum(1.0, m / np.maximum(covered, tiny))
    theta_spin = np.ones(n) if explicit else np.minimum(1.0, inertia / np.maximum(moment, tiny))
    dv = (dt * external.force + impulse[:, :3]) / (m + (1 - theta) * covered)[:, None]
    dw = (dt * external.torque + impulse[:, 3:]) / (inertia + (1 - theta_spin) * moment)[:, None]
    return dv, dw


def hydrodynamic_force(state: ParticleState, external: External, dv: np.ndarray, dw: np.ndarray,
                       impulse: np.ndarray, dt: float):
    """The step's hydrodynamic force and torque (n, 3) on each particle: from its velocity changes
    (free particles, so that m ΔV = dt (F + F_ext)) or the impulse exchanged (fixed, prescribed)."""
    free = state.movable
    force = np.where(free[:, None], state.mass[:, None] * dv / dt - external.force, impulse[:, :3] / dt)
    torque = np.where(free[:, None], state.inertia[:, None] * dw / dt - external.torque, impulse[:, 3:] / dt)
    return force, torque


def watch_ringing(state: ParticleState, change: np.ndarray, memory: CouplingMemory, fluid_density: float,
                  step: int, time: float, holders) -> CouplingMemory:
    """Collective. The explicit update's watchdog: a particle whose velocity change (n, 3) flips sign
    and grows 4 steps running rings (the light-particle instability): NumericalError on every rank.
    Returns ``memory`` with this step's changes and counts, by id, for the next step."""
    position, known = by_id(memory.ringing_id, state.id)
    last = memory.last_change[position] if known.any() else np.zeros_like(change)
    count = memory.ringing[position] if known.any() else np.zeros(len(state), np.int64)
    size, before = np.linalg.norm(change, axis=1), np.linalg.norm(last, axis=1)
    flips = known & (np.einsum("ij,ij->i", change, last) < 0)
    growing = flips & (size > 1.5 * before) & (size > 1e-9)
    ringing = np.where(growing, count + 1, 0)
    error = None
    if (ringing >= 4).any():
        i = int(np.argmax(ringing))
        error = NumericalError(
            f"step {step}, t = {time:.6g} s: particle {state.id[i]} (density ratio "
            f"{state.density[i] / fluid_density:.3g}) rings: its velocity change flips sign and grows every "
            "step, the explicit coupling instability of light particles; use [coupling] update = "
            "\"implicit\" (the default), or a smaller [run] dt")
    if holders.halo is not None:   # (where every rank holds every particle, every rank sees it)
        agree(holders.comm, error)
    elif error is not None:
        raise error
    order = np.argsort(state.id)
    return replace(memory, ringing_id=state.id[order], last_change=change[order], ringing=ringing[order])
