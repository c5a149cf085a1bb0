"""Stage 8: particles that left the domain are removed; where ranks own particles (runs on several
ranks), those whose centre entered another rank's box migrate to it
(ARCHITECTURE.md, "Particles"; ``pmpm.ownership`` holds the boxes and the exchanges).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .collisions import ContactMemory, jit
from .collisions.walls import particles_bounce
from .errors import NumericalError
from .ownership import IMBALANCE, bisect, exchange_groups, particle_rows, particles_of
from .particles import ParticleState
from .state import RunState


def remove_outside(model, state: RunState, start: np.ndarray) -> RunState:
    """Collective. Where every rank holds every particle: particles whose centre left the domain
    (``model.mesh``) are removed (counted in ``removed``, and in ``removed_through`` by the boundary
    each crossed on its way from ``start``, (n, 3) the positions the step started from, rows as the
    particles'; ``model.exits``: ``pmpm.exits.ExitFaces``)."""
    if len(state.particles) == 0:
        return state
    outside = ~model.mesh.inside_domain(state.particles.x)
    if not outside.any():
        return state
    removed_through = state.removed_through
    if model.exits is not None:
        removed_through = model.exits.count(start[outside], state.particles.x[outside], removed_through)
    return replace(state, particles=state.particles.without(outside), removed=state.removed + int(outside.sum()),
                   removed_through=removed_through, hydro_force=state.hydro_force[~outside],
                   hydro_torque=state.hydro_torque[~outside])


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


def exit_triangles(case, mesh) -> tuple:
    """Collective. The boundary triangles particles can leave the domain through, the same on every
    rank: those that are not walls to them (``particles_bounce``), every one without [collisions];
    as (a, b, c) vertices (m, 3) each and the unit normal into the domain (m, 3)."""
    names = [name for name in mesh.boundary_names
             if not case.collisions or not particles_bounce(case.boundaries.get(name))]
    triangles, _, normal = mesh.boundary_triangles(names)
    return triangles[:, 0], triangles[:, 1], triangles[:, 2], normal


def crossed_exits(exits: tuple, particles: ParticleState, dt: float, inside: np.ndarray | None = None) -> np.ndarray:
    """Local. (n,) bool: the particles whose centre crossed an exit triangle (``exit_triangles``) in
    the last step of ``dt``: those within their travel of an exit, on its far side from the domain.
    ``inside`` (n,) bool, optional: particles known to be inside the domain (e.g. in this rank's
    cells), which are not tested.

    Where ranks own particles, this replaces the point location in every rank's cells (a particle's
    rank is not the rank of its cell): a particle inside the domain leaves only through a boundary
    that is not a wall to it, and the one it just crossed is within its last step's travel."""
    a, b, c, normal = exits
    x = particles.x
    outside = np.zeros(len(x), bool)
    if len(a) == 0 or len(x) == 0 or (inside is not None and inside.all()):
        return outside
    travel = 1.5 * np.linalg.norm(particles.v, axis=1) * dt + 1e-9 * particles.radius
    corners = np.concatenate([a, b, c])
    low, high = corners.min(axis=0), corners.max(axis=0)
    near = ((x >= low - travel[:, None]) & (x <= high + travel[:, None])).all(axis=1)
    near = np.flatnonzero(near if inside is None else near & ~inside)
    if len(near) == 0:
        return outside
    face, q = jit.kernels().contact_times.nearest_faces(x[near], a, b, c)   # each one's closest exit triangle
    offset = x[near] - q
    beyond = np.einsum("ij,ij->i", offset, normal[face]) < 0
    outside[near[beyond & (np.linalg.norm(offset, axis=1) <= travel[near])]] = True
    return outside


def migrate_particles(comm, exits: tuple, exit_faces, state: RunState, start: np.ndarray, dt: float,
                      rebalance: bool = True, inside: np.ndarray | None = None) -> RunState:
    """Collective. Where ranks own particles, stage 8 in one gather of counts and (when a particle
    changed rank) one exchange: the particles that crossed an exit are removed (``crossed_exits``),
    the ones whose centre entered another rank's box go to it, with their last hydrodynamic force
    and the contact memory of the contacts whose lower-id particle they are; when a rank owns more
    than ``ownership.IMBALANCE`` × the mean, the boxes are bisected again first (with ``rebalance``;
    in a flow the boxes are the mesh's, and stay). ``inside``: as in ``crossed_exits``. A particle whose
    state is not finite stops the run on every rank (NumericalError). The removed are counted by
    the boundary their path from ``start`` (the step's first positions, rows as the particles')
    crossed (``exit_faces``: ``pmpm.exits.ExitFaces``, or None), summed over ranks."""
    partition = state.partition
    outside = crossed_exits(exits, state.particles, dt, inside)
    through = (exit_faces.count(start[outside], state.particles.x[outside], {})
               if exit_faces is not None and outside.any() else {})
    particles = state.particles.without(outside)
    force, torque = state.hydro_force[~outside], state.hydro_torque[~outside]
    owner = partition.owner_of(particles.x)
    gathered = comm.allgather(((len(particles), int((owner != comm.rank).sum()), int(outside.sum()),
                                first_not_finite(particles)), through))
    counts = np.array([rank_counts for rank_counts, _ in gathered])
    if (counts[:, 3] >= 0).any():
        raise not_finite(int(counts[np.argmax(counts[:, 3] >= 0), 3]), state.step + 1, state.time + dt)
    removed_through = dict(state.removed_through)
    for _, rank_through in gathered:
        for name, n in rank_through.items():
            removed_through[name] = removed_through.get(name, 0) + n
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
