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
    # the state's new parts, taken in one replace at the end
    changes = dict(removed=state.removed + int(counts[:, 2].sum()),
                   removed_through=counts_added(state.removed_through, through))
    if rebalance and counts[:, 0].max() > IMBALANCE * max(counts[:, 0].mean(), 1.0) and counts[:, 0].max() >= 64:
        each = particle_work(particles.id, remembered.first_id, remembered.second_id)
        partition = bisect(comm, particles.x[~outside], work=each[~outside])
        owner = np.where(outside, -1, partition.owner_of(particles.x))
        changes["partition"] = partition
    elif counts[:, 1].sum() == 0:
        if outside.any():
            changes.update(particles=particles.without(outside), hydro_force=state.hydro_force[~outside],
                           hydro_torque=state.hydro_torque[~outside])
        return replace(state, **changes)
    gone = np.flatnonzero(owner != comm.rank)     # removed (owner −1), or to another rank
    hydro = (state.hydro_force, state.hydro_torque)
    groups = [(owner[gone], packed(particles, gone, *hydro))]
    contacts = state.contacts
    if contacts is not None:   # the memory goes where the contact's lower-id particle goes
        begin = np.searchsorted(contacts.first_id, particles.id[gone], "left")   # each one's contacts: a range
        count = np.searchsorted(contacts.first_id, particles.id[gone], "right") - begin
        follows = np.repeat(begin - np.cumsum(count) + count, count) + np.arange(count.sum())
        groups.append((np.repeat(owner[gone], count), contacts.packed(follows)))
    (arrived, _), *arrived_contacts = exchanged(comm, *groups)
    keep = np.ones(len(particles), bool)
    keep[gone] = False
    particles, _, _, (force, torque) = merged(particles, arrived, keep, hydro)
    changes.update(particles=particles, hydro_force=force, hydro_torque=torque)
    if contacts is not None and (len(follows) or len(arrived_contacts[0][0])):
        changes["contacts"] = spliced(contacts, follows, arrived_contacts[0][0])
    return replace(state, **changes)


def spliced(memory: ContactMemory, drop: np.ndarray, block: np.ndarray) -> ContactMemory:
    """``memory`` less its rows ``drop`` (indices), with the contacts of ``block`` (rows as from
    ``ContactMemory.packed``, any order) in their places by (first_id, second_id): one compiled merge (a
    step's migration changes a few rows of thousands)."""
    added = ContactMemory.of_packed(block)
    keep = np.ones(len(memory), bool)
    keep[drop] = False
    n = int(keep.sum()) + len(added)
    result = ContactMemory(np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n), np.empty((n, 3)))
    _splice((memory.first_id, memory.second_id, memory.normal_impulse, memory.tangential_impulse), keep,
            (added.first_id, added.second_id, added.normal_impulse, added.tangential_impulse),
            (result.first_id, result.second_id, result.normal_impulse, result.tangential_impulse))
    return result


@njit(cache=True)
def _splice(kept, keep, added, out):
    """The rows of ``kept`` where ``keep`` and all of ``added`` (each a memory's (first, second,
    normal, tangential), sorted by (first, second)) merged by (first, second) into ``out``, an added
    row before a kept one of the same key."""
    first, second, normal, tangential = kept
    new_first, new_second, new_normal, new_tangential = added
    out_first, out_second, out_normal, out_tangential = out
    n, m = len(first), len(new_first)
    i, j = 0, 0
    for k in range(len(out_first)):
        while i < n and not keep[i]:
            i += 1
        take_added = j < m and (i == n or new_first[j] < first[i]
                                or (new_first[j] == first[i] and new_second[j] <= second[i]))
        if take_added:
            out_first[k], out_second[k], out_normal[k] = new_first[j], new_second[j], new_normal[j]
            for d in range(3):
                out_tangential[k, d] = new_tangential[j, d]
            j += 1
        else:
            out_first[k], out_second[k], out_normal[k] = first[i], second[i], normal[i]
            for d in range(3):
                out_tangential[k, d] = tangential[i, d]
            i += 1
