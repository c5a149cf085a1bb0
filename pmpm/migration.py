"""Stage 8: particles that left the domain are removed; where ranks own particles (runs on several
ranks), those whose centre entered another rank's box migrate to it
(ARCHITECTURE.md, "Particles"; ``pmpm.ownership`` holds the boxes, ``pmpm.packed`` moves the rows).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from numba import njit

from .collisions import ContactMemory
from .errors import NumericalError
from .ownership import IMBALANCE, bisect, particle_work, rank_work
from .packed import exchanged, merged, packed
from .particles import ParticleState
from .state import RunState


def crossings(exits, state: RunState, start: np.ndarray) -> np.ndarray:
    """Local. (n,) int, the boundary (an index into ``exits.names``) that each particle's centre's
    path from ``start`` (n, 3), the step's first positions, rows as the particles', crossed
    outwards, −1 for none (``exits``: ``pmpm.exits.BoundaryFaces``, or None where no particle can
    leave)."""
    if exits is None or len(state.particles) == 0:
        return np.full(len(state.particles), -1)
    return exits.crossed(start, state.particles.x)


def remove_outside(exits, state: RunState, start: np.ndarray) -> RunState:
    """Local. Where every rank holds every particle (1 rank): the particles that left the domain
    (``crossings``) are removed, counted in ``removed`` and in ``removed_through``."""
    crossed = crossings(exits, state, start)
    outside = crossed >= 0
    if not outside.any():
        return state
    through = exits.count(crossed[outside])
    return replace(state, particles=state.particles.without(outside), removed=state.removed + int(outside.sum()),
                   removed_through=counts_added(state.removed_through, through),
                   hydro_force=state.hydro_force[~outside], hydro_torque=state.hydro_torque[~outside])


def counts_added(totals: dict, more: dict) -> dict:
    """Counts by name: ``totals`` with ``more`` added."""
    totals = dict(totals)
    for name, n in more.items():
        totals[name] = totals.get(name, 0) + n
    return totals


def first_not_finite(particles: ParticleState, among: np.ndarray | None = None) -> int:
    """The id of the first particle (``among``: of those where true) whose position or velocity is not
    finite, or −1."""
    among = np.ones(len(particles), bool) if among is None else among
    return int(_first_not_finite(particles.id, particles.x, particles.v, among))


@njit(cache=True)
def _first_not_finite(pid, x, v, among):
    """``first_not_finite``, compiled (every step asks it of every particle)."""
    for i in range(len(pid)):
        if among[i]:
            for d in range(3):
                if not (np.isfinite(x[i, d]) and np.isfinite(v[i, d])):
                    return pid[i]
    return -1


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
    changed rank) one exchange: the particles whose path crossed the domain's boundary are removed
    (``crossings``; the counts summed over ranks), the ones whose centre entered another rank's
    box go to it, with their last hydrodynamic force and the contact memory of the contacts whose
    lower-id particle they are; when a rank's work (``ownership.particle_work``: its particles and the remembered
    contacts they solve) is more than ``ownership.IMBALANCE`` × the mean, the boxes are bisected
    again by work first (with ``rebalance``; in a flow the boxes are the mesh's, and stay). A
    particle whose state is not finite stops the run on every rank (NumericalError). The rows that
    leave go packed in one block (``pmpm.packed``), and those that arrive are merged in by id."""
    partition = state.partition
    particles = state.particles
    names = exits.names if exits is not None else ()
    crossed = crossings(exits, state, start)
    outside = crossed >= 0
    owner = partition.owner_of(particles.x)
    owner[outside] = -1
    to_others = int((owner >= 0).sum() - (owner == comm.rank).sum())
    remembered = state.contacts if state.contacts is not None else ContactMemory.empty()
    work = rank_work(len(particles) - int(outside.sum()), remembered.second_id)
    # per rank: its work, the particles it sends, removes, the first not finite, those out through each boundary
    mine = np.array([work, to_others, outside.sum(), first_not_finite(particles, ~outside),
                     *np.bincount(crossed[outside], minlength=len(names))], float)
    counts = np.empty((comm.size, len(mine)))
    comm.Allgather(mine, counts)
    if (counts[:, 3] >= 0).any():
        raise not_finite(int(counts[np.argmax(counts[:, 3] >= 0), 3]), state.step + 1, state.time + dt)
    through = {name: int(n) for name, n in zip(names, counts[:, 4:].sum(axis=0)) if n > 0}
    state = replace(state, removed=state.removed + int(counts[:, 2].sum()),
                    removed_through=counts_added(state.removed_through, through))
    if rebalance and counts[:, 0].max() > IMBALANCE * max(counts[:, 0].mean(), 1.0) and counts[:, 0].max() >= 64:
        each = particle_work(particles.id, remembered.first_id, remembered.second_id)
        partition = bisect(comm, particles.x[~outside], work=each[~outside])
        owner = np.where(outside, -1, partition.owner_of(particles.x))
        state = replace(state, partition=partition)
    elif counts[:, 1].sum() == 0:
        if not outside.any():
            return state
        return replace(state, particles=particles.without(outside), hydro_force=state.hydro_force[~outside],
                       hydro_torque=state.hydro_torque[~outside])
    gone = np.flatnonzero(owner != comm.rank)     # removed (owner −1), or to another rank
    hydro = (state.hydro_force, state.hydro_torque)
    groups = [(owner[gone], packed(particles, gone, *hydro))]
    contacts = state.contacts
    if contacts is not None:   # the memory goes where the contact's lower-id particle goes
        begin = np.searchsorted(contacts.first_id, particles.id[gone], "left")   # each one's contacts: a range
        count = np.searchsorted(contacts.first_id, particles.id[gone], "right") - begin
        follows = np.repeat(begin - np.cumsum(count) + count, count) + np.arange(count.sum())
        groups.append((np.repeat(owner[gone], count), memory_rows(contacts, follows)))
    (arrived, _), *arrived_contacts = exchanged(comm, *groups)
    keep = np.ones(len(particles), bool)
    keep[gone] = False
    particles, _, _, (force, torque) = merged(particles, arrived, keep, hydro)
    state = replace(state, particles=particles, hydro_force=force, hydro_torque=torque)
    if contacts is not None and (len(follows) or len(arrived_contacts[0][0])):
        new = memory_arrays(arrived_contacts[0][0])
        memory = spliced(contacts.to_arrays(), contacts.keys, follows, new,
                         ContactMemory.key_of(new["first_id"], new["second_id"]))
        state = replace(state, contacts=ContactMemory.from_arrays(memory))
    return state


def memory_rows(contacts: ContactMemory, rows: np.ndarray) -> np.ndarray:
    """(len(rows), 6) the remembered contacts' ``rows`` as float64: first and second id, the normal
    impulse, the tangential impulse (ids exact below 2^53)."""
    return np.column_stack([contacts.first_id[rows], contacts.second_id[rows], contacts.normal_impulse[rows],
                            contacts.tangential_impulse[rows]]).astype(float)


def memory_arrays(block: np.ndarray) -> dict:
    """The inverse of ``memory_rows``: ``ContactMemory``'s fields by name."""
    return {"first_id": block[:, 0].astype(np.int64), "second_id": block[:, 1].astype(np.int64),
            "normal_impulse": block[:, 2].copy(), "tangential_impulse": block[:, 3:6].copy()}


def spliced(rows: dict, keys: np.ndarray, drop: np.ndarray, added: dict, added_keys: np.ndarray) -> dict:
    """``rows`` (arrays sorted by ``keys``) less the rows ``drop`` (indices, ascending) and with the
    rows ``added`` (any order) in their places by key: copied by slices between the rows that
    change (a step's migration changes a few rows of thousands; a boolean mask on rows of (n, 3)
    took 20 times a copy's time)."""
    order = np.argsort(added_keys, kind="stable")
    at = np.searchsorted(keys, added_keys[order])
    # pieces in the order of the result: (start, stop) a range of the old rows, j the j-th added row
    pieces, cursor = [], 0
    events = sorted([(int(p), 0, j) for j, p in enumerate(at)] + [(int(d), 1, 0) for d in drop])
    for position, dropping, j in events:
        if position > cursor:
            pieces.append((cursor, position))
        cursor = max(cursor, position + dropping)
        if not dropping:
            pieces.append(j)
    pieces.append((cursor, len(keys)))
    result = {}
    for name, values in rows.items():
        new = added[name][order]
        result[name] = np.concatenate([values[p[0]:p[1]] if isinstance(p, tuple) else new[p:p + 1] for p in pieces])
    return result
