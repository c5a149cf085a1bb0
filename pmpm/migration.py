"""Stage 8: particles that left the domain are removed; where ranks own particles (runs on several
ranks), those whose centre entered another rank's box migrate to it
(ARCHITECTURE.md, "Particles"; ``pmpm.ownership`` holds the boxes and the exchanges).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .collisions import ContactMemory
from .errors import NumericalError
from .ownership import IMBALANCE, bisect, exchange_groups, particle_rows, particles_of
from .particles import ParticleState
from .state import RunState


def leaving(exits, state: RunState, start: np.ndarray) -> tuple[np.ndarray, dict]:
    """Local. (n,) bool, the particles whose centre's path from ``start`` (n, 3), the step's first
    positions, rows as the particles', crossed the domain's boundary (``exits``:
    ``pmpm.exits.BoundaryFaces``, or None where no particle can be), and how many crossed each
    boundary (name → count)."""
    if exits is None or len(state.particles) == 0:
        return np.zeros(len(state.particles), bool), {}
    crossed = exits.crossed(start, state.particles.x)
    outside = crossed >= 0
    return outside, exits.count(crossed[outside])


def remove_outside(exits, state: RunState, start: np.ndarray) -> RunState:
    """Local. Where every rank holds every particle (1 rank): the particles that left the domain
    (``leaving``) are removed, counted in ``removed`` and in ``removed_through``."""
    outside, through = leaving(exits, state, start)
    if not outside.any():
        return state
    return replace(state, particles=state.particles.without(outside), removed=state.removed + int(outside.sum()),
                   removed_through=merged(state.removed_through, through), hydro_force=state.hydro_force[~outside],
                   hydro_torque=state.hydro_torque[~outside])


def merged(totals: dict, more: dict) -> dict:
    """Counts by name: ``totals`` with ``more`` added."""
    totals = dict(totals)
    for name, n in more.items():
        totals[name] = totals.get(name, 0) + n
    return totals


def first_not_finite(particles: ParticleState) -> int:
    """The id of the first particle whose position or velocity is not finite, or −1."""
    bad = ~np.isfinite(particles.x).all(axis=1) | ~np.isfinite(particles.v).all(axis=1)
    return int(particles.id[np.argmax(bad)]) if bad.any() else -1


def not_finite(pid: int, step: int, time: float) -> NumericalError:
    return NumericalError(f"step {step}, t = {time:.6g} s: particle {pid} has a non-finite position or velocity; "
                          "reduce [run] dt")


def check_finite(particles: ParticleState, step: int, time: float) -> None:
    """Raise NumericalError naming the first particle whose state is not finite."""
    pid = first_not_finite(particles)
    if pid >= 0:
        raise not_finite(pid, step, time)


def migrate_particles(comm, exits, state: RunState, start: np.ndarray, dt: float, rebalance: bool = True) -> RunState:
    """Collective. Where ranks own particles, stage 8 in one gather of counts and (when a particle
    changed rank) one exchange: the particles that left the domain are removed (``leaving``, the
    counts summed over ranks), the ones whose centre entered another rank's box go to it, with
    their last hydrodynamic force and the contact memory of the contacts whose lower-id particle
    they are; when a rank owns more than ``ownership.IMBALANCE`` × the mean, the boxes are bisected
    again first (with ``rebalance``; in a flow the boxes are the mesh's, and stay). A particle whose
    state is not finite stops the run on every rank (NumericalError)."""
    partition = state.partition
    outside, through = leaving(exits, state, start)
    particles = state.particles.without(outside)
    force, torque = state.hydro_force[~outside], state.hydro_torque[~outside]
    owner = partition.owner_of(particles.x)
    gathered = comm.allgather(((len(particles), int((owner != comm.rank).sum()), int(outside.sum()),
                                first_not_finite(particles)), through))
    counts = np.array([rank_counts for rank_counts, _ in gathered])
    if (counts[:, 3] >= 0).any():
        raise not_finite(int(counts[np.argmax(counts[:, 3] >= 0), 3]), state.step + 1, state.time + dt)
    removed_through = state.removed_through
    for _, rank_through in gathered:
        removed_through = merged(removed_through, rank_through)
    state = replace(state, removed=state.removed + int(counts[:, 2].sum()), removed_through=removed_through)
    if rebalance and counts[:, 0].max() > IMBALANCE * max(counts[:, 0].mean(), 1.0) and counts[:, 0].max() >= 64:
        partition = bisect(comm, particles.x)
        owner = partition.owner_of(particles.x)
    elif counts[:, 1].sum() == 0:
        return replace(state, particles=particles, hydro_force=force, hydro_torque=torque)
    contacts = state.contacts
    groups = [(owner, {**particle_rows(particles), "hydro_force": force, "hydro_torque": torque})]
    if contacts is not None:   # the memory goes where the contact's lower-id particle goes
        at = np.searchsorted(particles.id, contacts.first_id)
        held = at < len(particles)
        held[held] = particles.id[at[held]] == contacts.first_id[held]
        groups.append((np.where(held, owner[np.minimum(at, len(particles) - 1)] if len(particles) else -1, -1),
                       contacts.to_arrays()))
    moved, *kept = exchange_groups(comm, groups)
    order = np.argsort(moved["id"], kind="stable")
    particles = particles_of(moved)
    state = replace(state, particles=particles, hydro_force=moved["hydro_force"][order],
                    hydro_torque=moved["hydro_torque"][order], partition=partition)
    if contacts is not None:
        kept = kept[0]
        order = np.argsort(ContactMemory.key_of(kept["first_id"], kept["second_id"]), kind="stable")
        state = replace(state, contacts=ContactMemory.from_arrays({k: v[order] for k, v in kept.items()}))
    return state
