"""The contact engine on subdomains: each rank moves the particles it owns, with ghost copies of
the particles of other ranks within contact range (docs/collisions.md, "Particles owned by ranks").

Every rank builds the contact record over its owned and ghost particles (sorted by id, so every
record is in the order of the 1-rank record restricted to it), keeping the contacts with at least
one owned particle; the ranks agree on the step's search speed and on the regime (the contacts that
can act, counted once each, by the owner of their lower-id particle). Then:

- a **dense step with many contacts** (a bed, a hopper: at least ``gather_contacts`` that can act,
  over all ranks) is a block Gauss–Seidel that conforms to the subdomains (Preclik & Rüde 2015): a
  contact is solved by the rank that owns its lower-id particle (walls: the particle's owner), each
  rank sweeps its contacts in the record's order, and the ranks' sweeps follow one another in one
  order: the ranks are coloured (two holding a particle together apart), and in each sweep a rank
  sweeps its *border* contacts (touching a particle another rank holds) after taking the lower
  colours' copies of the shared particles, passes its copies on, and sweeps its *inner* contacts
  while the higher colours sweep their border (a rank with lower colours sweeps the first half of
  its inner contacts before its border, while they sweep theirs; ``block_sweeps``; one message each
  way per pair of ranks sharing particles, per sweep). So a sweep over all ranks is a Gauss–Seidel
  sweep of one rank over the contacts ordered by colour, the copies stay equal to the bit, and each
  rank takes the nonsmooth conjugate-gradient step of its contacts after each sweep, as one rank
  does (its own step length). The stopping test, the energy check and the deposition flags meet in
  reductions, so every rank makes the same number of sweeps. Overlaps are removed per rank over its
  contacts (positions, each rank keeping its owned particles').
- any other step (an event step, or a dense one with fewer contacts) gathers the particles of
  every contact, from their owners, on every rank, which all take the same step
  (``advance_with_collisions``, with the global search speed and particle count) and keep their
  owned particles' results: the gather is bounded by the contacts, and such steps (impacts in
  time order, a pair or a column across the cut, a small pile) give the 1-rank result to the bit.

On one rank this is ``advance_with_collisions`` itself.
"""
from __future__ import annotations

import numpy as np
from mpi4py import MPI

from . import jit, messages
from .record import ContactMemory
from .search import find_contacts, travel_of, wall_arrays
from .dense import finish, solve_start, targets
from .settings import COLD_SWEEPS, ENERGY_TOL, SEARCH_SLACK, SWEEP_TOL, CollisionSettings
from .solver import Bodies, ContactStep, advance_with_collisions, remove_overlaps
from .stats import CLAMPS, DEPOSITED, EXTRA, NAMES, SWEEPS, as_dict, new_counters
from .walls import Walls
from ..arrays import members
from ..halo import Halo, Pass
from ..ownership import Partition
from ..packed import gathered, merged, packed
from ..particles import FREE, ParticleState


def advance_owned(comm, partition: Partition, state: ParticleState, walls: Walls | None, dt: float,
                  settings: CollisionSettings, memory: ContactMemory | None = None) -> ContactStep:
    """Collective. ``advance_with_collisions`` for the particles this rank owns (``state``, updated
    in place) among every rank's; ``memory`` holds the contacts whose lower-id particle this rank
    owns, and so does the returned one. ``stats`` are the same on every rank (summed over ranks),
    with ``owned``, ``ghosts`` and ``exchanged_bytes`` (sent in the step's ghost exchanges) added,
    this rank's."""
    if comm.size == 1:
        return advance_with_collisions(state, walls, dt, settings, memory)
    dt = float(dt)
    memory = ContactMemory.empty() if memory is None else memory
    walls_after = walls.moved(dt) if walls is not None else None
    kernels = jit.kernels()
    free_anywhere, top, r_max, population, remembered = reduced(
        comm, sum_of=(len(state), len(memory)),
        max_of=(float(state.movable.any()), state.top_speed(), float(state.radius.max(initial=0.0))))
    population = int(round(population))
    used_walls = walls if walls is not None and len(walls) and free_anywhere else None
    wall_speed = float(used_walls.top_speed.max()) if used_walls is not None else 0.0
    speed = max(SEARCH_SLACK * top, settings.rest_speed, 2.0 * wall_speed)
    reach = 2.0 * speed * dt
    full_width = (state.radius + r_max + reach) * (1 + 1e-9)
    # A dense step needs only the pairs that can act, closer than r_i + r_j + each one's travel
    # (``find_contacts``): its ghosts are the particles within r + r_max + their travel + the
    # largest travel of a rank's box. Taken where the last step was dense (its memory that large);
    # a step that turns out not dense builds the ghosts of the full reach.
    dense_likely = settings.dense_contacts > 0 and remembered >= max(settings.gather_contacts, 1)
    width = full_width
    if dense_likely:
        travel = kernels.step_arrays.travels(state.v, state.moving, dt, reach)
        width = (state.radius + r_max + travel + travel_of(top, dt, reach)) * (1 + 1e-9)
    search = (comm, partition, state, used_walls, dt, reach, settings, kernels)
    halo, local, bodies, (record, dense, acting) = ghosts_and_contacts(*search, width, dense_likely)
    if not dense or acting < settings.gather_contacts:
        sent = 0
        if dense_likely:   # the same search over the ghosts of the full reach
            sent = halo.sent
            halo, local, bodies, (record, _, _) = ghosts_and_contacts(*search, full_width, dense_likely=False)
        step = gathered_step(comm, state, local, halo, record, walls, dt, settings, memory, speed, population)
        step.stats.update(owned=len(state), ghosts=len(local) - len(state), exchanged_bytes=sent + halo.sent)
        return step
    n = len(local)
    owned = np.append(halo.owned, False)              # the world row last
    extra = {"owned": len(state), "ghosts": n - len(state)}
    counters = new_counters()
    warm_n, warm_t = memory.recall(record, local.id)
    mine = owned[record.first]
    lam_n, lam_t = dense_blocks(halo, bodies, record, np.flatnonzero(mine), warm_n, warm_t, settings, dt,
                                used_walls, kernels, counters, extra)
    remove_overlaps(bodies, record, walls_after, kernels, extra, reach, thorough=False)
    rows = np.flatnonzero(halo.owned)
    bodies.x.take(rows, axis=0, out=state.x)
    np.copyto(state.v, bodies.v.take(rows, axis=0), where=(state.motion == FREE)[:, None])
    bodies.w.take(rows, axis=0, out=state.omega)
    bodies.deposited.take(rows, out=state.deposited)
    memory = ContactMemory.remember(record, local.id, lam_n, lam_t, mine)
    extra["exchanged_bytes"] = halo.sent
    return ContactStep(summed_stats(comm, counters, extra), memory, walls_after)


def ghosts_and_contacts(comm, partition, state, walls, dt, reach, settings, kernels, width, dense_likely) -> tuple:
    """Collective. The ghosts within ``width`` (per owned particle, m) of each rank's box, and the
    contacts among the local particles: (halo, local particles, their ``Bodies``, ``find_contacts``'
    (record, dense, acting)), searched by travel first where the step is ``dense_likely``."""
    halo, local = Halo.build(comm, partition, state, width)
    bodies = Bodies.of(local)
    found = find_contacts(bodies, walls, dt, reach, settings.restitution, settings.friction, kernels,
                          dense_contacts=settings.dense_contacts, owned=halo.owned, comm=comm,
                          dense_likely=dense_likely)
    return halo, local, bodies, found


def reduced(comm, max_of: tuple, sum_of: tuple) -> list:
    """Collective. The maxima over ranks of ``max_of`` and the sums of ``sum_of``, from one gather."""
    values = np.array(max_of + sum_of, float)
    every = np.empty((comm.size, len(values)))
    comm.Allgather(values, every)
    maxima, sums = every[:, :len(max_of)].max(axis=0), every[:, len(max_of):].sum(axis=0)
    return [float(v) for v in maxima] + [float(v) for v in sums]


def summed_stats(comm, counters: np.ndarray, extra: dict) -> dict:
    """Collective. The step's counts summed over ranks (sweeps and dense steps: the same on every rank)."""
    names = [name for name in EXTRA if name != "dense_steps"]
    values = np.concatenate([counters, [extra.get(name, 0) for name in names]]).astype(np.int64)
    total = np.empty_like(values)
    comm.Allreduce(values, total, op=MPI.SUM)
    total[SWEEPS] = counters[SWEEPS]
    summed = dict(zip(names, total[len(NAMES):]))
    stats = as_dict(total[:len(NAMES)], {**summed, "dense_steps": extra.get("dense_steps", 0)})
    stats.update(owned=extra["owned"], ghosts=extra["ghosts"], exchanged_bytes=extra["exchanged_bytes"])
    return stats


# ----------------------------------------------------------------------------------------------
# Few contacts: the contacts' particles gathered, one step on every rank
# ----------------------------------------------------------------------------------------------
def gathered_step(comm, state, local, halo, record, walls, dt, settings, memory, speed, population) -> ContactStep:
    """Collective. The step of the particles in contact (``record``'s), gathered from their owners on
    every rank and moved there identically; the other owned particles fly freely."""
    n = len(local)
    involved = np.zeros(n + 1, bool)
    involved[record.first] = True
    involved[record.second] = True
    sending = np.flatnonzero(involved[:n] & halo.owned)
    # the memory of the contacts of the particles sent (those whose lower-id particle is owned here)
    held = np.flatnonzero(members(memory.first_id, local.id[sending]))
    sent = (packed(local, sending), memory.packed(held))
    halo.sent += (comm.size - 1) * sum(block.nbytes for block in sent)
    particles, contacts = gathered(comm, *sent)
    cluster = merged(ParticleState.empty(), particles)[0]   # (sorted by id)
    memory = ContactMemory.of_packed(contacts)
    result = advance_with_collisions(cluster, walls, dt, settings, memory, speed=speed, population=population)
    # owned particles out of every contact fly at their velocity (fixed and deposited ones stay)
    moving = state.moving
    state.x[moving] += state.v[moving] * dt
    at = np.searchsorted(cluster.id, state.id)
    found = at < len(cluster)
    found[found] = cluster.id[at[found]] == state.id[found]
    rows, source = np.flatnonzero(found), at[found]
    for name in ("x", "v", "omega", "deposited"):
        getattr(state, name)[rows] = getattr(cluster, name)[source]
    kept = result.memory.take(members(result.memory.first_id, state.id))
    return ContactStep(dict(result.stats), kept, result.walls)


# ----------------------------------------------------------------------------------------------
# The dense regime: block Gauss–Seidel over the subdomains
# ----------------------------------------------------------------------------------------------
def dense_blocks(halo: Halo, bodies, record, rows, warm_n, warm_t, settings, dt, walls, kernels, counters, extra):
    """``dense.dense_step`` over this rank's contacts ``rows`` (those whose ``first`` it owns), the
    ranks' sweeps in one order (see the module's docstring). Returns the
    contacts' impulses (m,) and (m, 3) (N s, on ``first``; 0 on other ranks' contacts)."""
    comm, impulses = halo.comm, kernels.impulses
    first, second, triangle = record.first, record.second, record.triangle
    rows = rows[~kernels.narrow.parallel_duplicates(rows, first, triangle, record.gap, record.normal, bodies.radius)]
    wall = triangle >= 0
    r_first = bodies.radius[first]
    r_second = np.where(wall, 0.0, bodies.radius[second])
    deposition = wall_arrays(walls)[9]
    if deposition.any():   # (the same on every rank)
        deposit(halo, bodies, record, rows, r_first, deposition, kernels, counters)
    v, w, inv_m, inv_i = bodies.v, bodies.w, bodies.inv_m, bodies.inv_i
    normal = record.normal
    touching, hits, target, hit_time, closing_speed = targets(bodies, record, rows, r_first, r_second, settings, dt)
    lam_n, lam_t, remembered, members, driven = solve_start(bodies, record, rows, warm_n, warm_t, walls)
    owned_members = members[halo.owned[members]]
    v0, w0 = v.copy(), w.copy()
    scale = max(closing_speed, settings.rest_speed, 1e-300)
    tol = SWEEP_TOL * settings.rest_speed if settings.rest_speed > 0 else 1e-12 * scale
    remembered, driven, tol, energy = reduced(comm, max_of=(float(remembered), float(driven), tol),
                                              sum_of=(impulses.kinetic_energy(owned_members, inv_m, inv_i, v, w),))
    reference = (v.copy(), w.copy())
    if remembered:
        impulses.warm_start(rows, first, second, normal, r_first, r_second, record.friction, inv_m, inv_i, v, w,
                            lam_n, lam_t)
        halo.merge(reference, v, w)
    budget = settings.dense_sweeps if remembered else COLD_SWEEPS * settings.dense_sweeps
    contacts = (first, second, normal, r_first, r_second, record.wall_velocity)
    sweeps = block_sweeps(halo, rows, contacts, target, record.friction, (inv_m, inv_i, v, w), lam_n, lam_t,
                          budget, tol, kernels)
    after = np.array([impulses.kinetic_energy(owned_members, inv_m, inv_i, v, w)])   # (summed over ranks)
    comm.Allreduce(MPI.IN_PLACE, after, op=MPI.SUM)
    if not driven and after[0] > energy * (1 + ENERGY_TOL) + 1e-300:
        # Newton's law over simultaneous contacts, or the ranks' blocks, can make energy: every
        # impulse scaled back (velocities and impulses alike) to the energy the bodies had
        counters[CLAMPS] += comm.rank == 0
        s = limit_energy(halo, owned_members, bodies, v0, w0, energy)
        lam_n *= s
        lam_t *= s
    finish(bodies, record, rows, lam_n, lam_t, v0, touching, hits, hit_time, dt, sweeps, counters, extra,
           wall_arrays(walls)[6], to_owners=halo.to_owners)
    extra["contacts"] = len(rows)
    return lam_n, lam_t


def block_sweeps(halo: Halo, rows, contacts, target, mu, bodies, lam_n, lam_t, budget: int, tol: float,
                 kernels) -> int:
    """Collective. Sweeps of this rank's contacts ``rows`` in one order over every rank's, until no
    owned body's contact-point velocity changed by more than ``tol`` (m/s) in a sweep, on any rank,
    or ``budget`` sweeps; returns the sweeps made (the same on every rank). ``bodies``: (1/m, 1/I,
    v, ω) per local row.

    A sweep is Gauss–Seidel over the ranks' contacts together: the ranks are coloured so that two
    holding a particle together differ, and a rank sweeps its *border* contacts (those touching a
    particle another rank holds) once the lower colours have sent theirs, sends its copies of the
    shared particles on, then sweeps its *inner* contacts (touching no shared particle) while the
    higher colours sweep their border, whose copies it takes at the end; a rank with lower colours
    sweeps the first half of its inner contacts before its border, while those sweep theirs (else a
    stall of a lower rank would hold it at once, each sweep). Inner contacts of different ranks
    share no body, so the sweep is that of one rank over the contacts ordered by colour (within a
    rank: the first half of its inner contacts where it has lower colours, its border, the rest),
    every contact seeing the velocities its bodies have just then, and the copies stay equal to the
    bit. Each rank's conjugate-gradient step (``impulses.sweep``'s notes, with this rank's step
    length: one reduced over the ranks converged no better) follows its inner sweep at once, and its
    border sweep's after the lower colours' copies arrive (before, it would be overwritten). A
    sweep's test is reduced over the ranks while the next two sweeps run (a nonblocking reduction,
    waited on once this rank has the higher colours' copies of the sweep after it, so every rank has
    started it: waiting one sweep sooner held the lowest colour until the highest finished its inner
    sweep, every sweep): the sweeps stop two sweeps after the one that converged.
    """
    first, second, normal, r_first, r_second, u_wall = contacts
    inv_m, inv_i, v, w = bodies
    impulses = kernels.impulses
    shared = np.zeros(len(inv_m), bool)
    shared[halo.shared_rows] = True
    # border and inner contacts; a rank changes the shared particles of its border contacts only
    # (``changing``): those it passes on each sweep
    border_rows, border_kn, border_kt, inner_rows, inner_kn, inner_kt, changing = impulses.split_at_shared(
        rows, shared, first, second, r_first, r_second, inv_m, inv_i)
    watched, arm = impulses.watched_bodies(rows, first, second, r_first, r_second, inv_m, np.append(halo.owned, False))
    colour = halo.colours()
    neighbours = sorted(halo.shared_at, key=lambda r: colour[r])
    passes = halo.passes(neighbours, changing)
    lower = sum(colour[r] < colour[halo.comm.rank] for r in neighbours)
    swept, sent_after, received_after = ([getattr(passes[r], name) for r in neighbours] for name in Pass._fields)
    passed = (*joined(swept), *joined(sent_after), *joined(received_after))
    done, _ = kernels.block.sweeps(
        (border_rows, border_kn, border_kt), (inner_rows, inner_kn, inner_kt), watched, arm,
        (first, second, normal, r_first, r_second, u_wall, target, mu), bodies, lam_n, lam_t,
        np.array(neighbours, np.int64), lower, passed, budget, tol, messages.handles(halo.comm))
    halo.sent += 6 * v.itemsize * (done * len(passed[0]) + len(passed[2]))   # (v, ω) per row passed
    return done


def joined(parts: list) -> tuple:
    """Arrays of rows, one after another, and the offsets where each begins (and the last ends)."""
    return (np.concatenate([np.zeros(0, np.int64), *parts]).astype(np.int64),
            np.cumsum([0] + [len(part) for part in parts]).astype(np.int64))


def limit_energy(halo: Halo, owned_members, bodies, v0, w0, energy: float) -> float:
    """Collective. ``impulses.limit_energy`` over the ranks: the velocity changes since (v0, w0)
    scaled back by the largest s in [0, 1] that keeps the kinetic energy of the owned bodies, summed
    over ranks, at ``energy``; returns s."""
    inv_m, inv_i, v, w = bodies.inv_m, bodies.inv_i, bodies.v, bodies.w
    k = owned_members[inv_m[owned_members] > 0]
    m, i = 1.0 / inv_m[k], 1.0 / inv_i[k]
    dv, dw = v[k] - v0[k], w[k] - w0[k]
    terms = np.array([(m[:, None] * dv * v0[k]).sum() + (i[:, None] * dw * w0[k]).sum(),
                      0.5 * ((m[:, None] * dv * dv).sum() + (i[:, None] * dw * dw).sum()),
                      0.5 * ((m[:, None] * v[k] * v[k]).sum() + (i[:, None] * w[k] * w[k]).sum())])
    halo.comm.Allreduce(MPI.IN_PLACE, terms, op=MPI.SUM)
    a, b, after = terms
    if after <= energy * (1 + ENERGY_TOL) + 1e-300:
        return 1.0
    s = min(1.0, -a / b) if b > 0 and a < 0 else 0.0
    v[:] = v0 + s * (v - v0)
    w[:] = w0 + s * (w - w0)
    return s


def deposit(halo: Halo, bodies, record, rows, r_first, deposition, kernels, counters) -> None:
    """Collective. Deposition over this rank's contacts, then every rank's new deposits on their
    owners and shadows alike (a particle deposited as another rank's ghost)."""
    n = len(bodies.radius) - 1
    changed = np.zeros(n + 1, np.int64)
    before = bodies.deposited[:n].copy()
    kernels.deposition.deposit_touching(rows, record.gap, r_first, bodies.kernel_tuple(),
                                        (record.first, record.second, record.triangle), deposition, changed,
                                        counters)
    flags = (bodies.deposited[:n] & ~before).astype(np.int64)
    counters[DEPOSITED] -= int(flags[~halo.owned].sum())     # counted by the owner
    halo.to_owners(flags)
    halo.to_ghosts(flags)
    now = np.flatnonzero((flags > 0) & ~bodies.deposited[:n])
    counters[DEPOSITED] += int(halo.owned[now].sum())
    bodies.v[now] = bodies.w[now] = 0.0     # as deposition.deposit
    bodies.inv_m[now] = bodies.inv_i[now] = 0.0
    bodies.free[now], bodies.deposited[now] = False, True
