"""Particles owned by ranks: the spatial partition, migration, ghost copies, gathering for output.

A particle belongs to the rank whose box holds its centre. In a flow the boxes are the mesh's
(``Mesh.part_boxes``), so the owner holds the particle's centre cell. Without a flow (DEM-only
runs) they are a recursive coordinate bisection of the *particles* (the mesh's own partition balances cells:
in the hopper its cut lies above nearly every particle), planes cutting the longest extent of the
particles in proportion to the ranks on each side, computed from histograms summed over ranks
(no rank ever holds every particle), and computed again when the particle counts drift apart
(``IMBALANCE``). The outer boxes reach to infinity, so every point has exactly one owner.

Each rank holds its owned particles (sorted by id) and, during a contact step, ghost copies of the
particles of other ranks within a given distance of its box (``Halo``): read-only copies whose
velocity changes go back to their owners (``Halo.merge``); in a flow, also ghost copies of the
particles that reach into its cells, whose per-particle sums meet among their holders
(``Halo.sum_over_holders``; ``pmpm.coupling.holders``).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from mpi4py import MPI
from numba import njit

from .particles import ParticleState

MAX_HOLDERS = 16       # the most ranks that may hold one particle (its owner and its ghosts')
IMBALANCE = 1.02        # the boxes are bisected again when a rank owns this × the mean number of particles
BINS, ROUNDS = 64, 3    # a cut is placed by ROUNDS histograms of BINS bins (to 1/64³ of the particles' extent)
PARTICLE_FIELDS = tuple(f.name for f in fields(ParticleState))


@dataclass(frozen=True)
class Partition:
    """Each rank's box, [lower, upper) per axis (m); the outer sides at ±inf. (ranks, 3) each."""

    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def whole(cls, ranks: int = 1) -> "Partition":
        """Every point on rank 0 (the boxes of the other ranks empty)."""
        lower, upper = np.full((ranks, 3), np.inf), np.full((ranks, 3), np.inf)
        lower[0], upper[0] = -np.inf, np.inf
        return cls(lower, upper)

    def owner_of(self, x: np.ndarray) -> np.ndarray:
        """(n,) int64, the rank whose box holds each point (n, 3); 0 for a point that is not finite."""
        return _owners(np.ascontiguousarray(x, float).reshape(-1, 3), self.lower, self.upper)

    def distance(self, x: np.ndarray) -> np.ndarray:
        """(n, ranks) distance (m) from each point to each rank's box (0 inside)."""
        return _box_distances(np.ascontiguousarray(x, float).reshape(-1, 3), self.lower, self.upper)

    def to_array(self) -> np.ndarray:
        return np.stack([self.lower, self.upper])

    @classmethod
    def from_array(cls, array: np.ndarray) -> "Partition":
        return cls(np.array(array[0], float), np.array(array[1], float))


@njit(cache=True)
def _owners(x, lower, upper):
    """``Partition.owner_of``, compiled (every step's migration asks it of every particle)."""
    owner = np.zeros(len(x), np.int64)
    for i in range(len(x)):
        for rank in range(len(lower)):
            if (lower[rank, 0] <= x[i, 0] < upper[rank, 0] and lower[rank, 1] <= x[i, 1] < upper[rank, 1]
                    and lower[rank, 2] <= x[i, 2] < upper[rank, 2]):
                owner[i] = rank
                break
    return owner


@njit(cache=True)
def _box_distances(x, lower, upper):
    """``Partition.distance``, compiled (every contact step's halo asks it of the particles near
    the box's sides); a coordinate that is not finite adds nothing, an empty box (inf) is at inf."""
    distance = np.zeros((len(x), len(lower)))
    for i in range(len(x)):
        for rank in range(len(lower)):
            squared = 0.0
            for axis in range(3):
                below, above = lower[rank, axis] - x[i, axis], x[i, axis] - upper[rank, axis]
                if below > 0:
                    squared += below * below
                elif above > 0:
                    squared += above * above
            distance[i, rank] = np.sqrt(squared)
    return distance


def bisect(comm, x: np.ndarray, domain: tuple | None = None) -> Partition:
    """Collective. Boxes that share the particles (centres ``x``, this rank's, (n, 3)) evenly among
    the ranks: each box with several ranks is cut across the longest extent of its particles, at
    the share of its ranks on the lower side, level by level (one set of reductions per level). A
    box without particles is cut across the middle of its part of ``domain`` ((lower, upper) (3,)
    each, m; the domain's bounding box), or at 0 without one."""
    ranks = comm.size
    nodes = [(np.full(3, -np.inf), np.full(3, np.inf), 0, ranks)]   # (lower, upper, first rank, ranks)
    while any(count > 1 for *_, count in nodes):
        split = [k for k, node in enumerate(nodes) if node[3] > 1]
        lower = np.array([nodes[k][0] for k in split])
        upper = np.array([nodes[k][1] for k in split])
        inside = ((x[:, None, :] >= lower[None]) & (x[:, None, :] < upper[None])).all(axis=2)
        node = np.where(inside.any(axis=1), np.argmax(inside, axis=1), -1)
        held = node >= 0
        low = np.full((len(split), 3), np.inf)
        high = np.full((len(split), 3), -np.inf)
        np.minimum.at(low, node[held], x[held])
        np.maximum.at(high, node[held], x[held])
        bounds = np.concatenate([low, -high], axis=1)
        comm.Allreduce(MPI.IN_PLACE, bounds, op=MPI.MIN)
        low, high = bounds[:, :3], -bounds[:, 3:]
        empty = ~np.isfinite(low).all(axis=1)
        low[empty], high[empty] = 0.0, 0.0
        if domain is not None:   # (the domain's part in the box)
            low[empty] = np.clip(domain[0], lower[empty], upper[empty])
            high[empty] = np.clip(domain[1], lower[empty], upper[empty])
        axis = np.argmax(high - low, axis=1)
        share = np.array([(nodes[k][3] // 2) / nodes[k][3] for k in split])
        coordinate = np.where(held, x[np.arange(len(x)), axis[np.maximum(node, 0)]] if len(x) else 0.0, 0.0)
        cut = quantile_cut(comm, coordinate, node, low[np.arange(len(split)), axis],
                           high[np.arange(len(split)), axis], share)
        children = []
        for k, (lo, hi, first, count) in enumerate(nodes):
            if count == 1:
                children.append(nodes[k])
                continue
            s = split.index(k)
            left = count // 2
            upper_left, lower_right = hi.copy(), lo.copy()
            upper_left[axis[s]] = lower_right[axis[s]] = np.clip(cut[s], lo[axis[s]], hi[axis[s]])
            children += [(lo, upper_left, first, left), (lower_right, hi, first + left, count - left)]
        nodes = children
    nodes.sort(key=lambda node: node[2])
    return Partition(np.array([node[0] for node in nodes]), np.array([node[1] for node in nodes]))


def quantile_cut(comm, coordinate: np.ndarray, node: np.ndarray, low: np.ndarray, high: np.ndarray,
                 share: np.ndarray) -> np.ndarray:
    """Collective. Per node, a coordinate below which ``share`` of its particles lie (``coordinate``
    and ``node`` per particle, node −1: in none), narrowed by ROUNDS histograms summed over ranks;
    the midpoint of [low, high] for a node without particles."""
    nodes = len(low)
    held = node >= 0
    lo, hi = low.astype(float).copy(), high.astype(float).copy()
    below = np.zeros(nodes)                       # particles below lo, per node
    total = np.bincount(node[held], minlength=nodes).astype(float)
    comm.Allreduce(MPI.IN_PLACE, total, op=MPI.SUM)
    target = share * total
    for _ in range(ROUNDS):
        width = np.maximum(hi - lo, 1e-300)
        b = np.floor((coordinate[held] - lo[node[held]]) / width[node[held]] * BINS).astype(np.int64)
        inside = (b >= 0) & (b < BINS)
        counts = np.bincount(node[held][inside] * BINS + b[inside], minlength=nodes * BINS).astype(float)
        comm.Allreduce(MPI.IN_PLACE, counts, op=MPI.SUM)
        running = below[:, None] + np.cumsum(counts.reshape(nodes, BINS), axis=1)
        k = np.minimum((running < target[:, None]).sum(axis=1), BINS - 1)   # the bin where the share is reached
        below = np.where(k > 0, running[np.arange(nodes), np.maximum(k - 1, 0)], below)
        lo, hi = lo + width * k / BINS, lo + width * (k + 1) / BINS
    return np.where(total > 0, hi, 0.5 * (low + high))


# ----------------------------------------------------------------------------------------------
# Moving rows between ranks
# ----------------------------------------------------------------------------------------------
def exchange_rows(comm, destination: np.ndarray, arrays: dict) -> dict:
    """Collective. Send row i of every array to rank ``destination[i]`` (−1: nowhere); returns the
    rows received from all ranks, in rank order, as a dict of arrays like ``arrays``."""
    return exchange_groups(comm, [(destination, arrays)])[0]


def exchange_groups(comm, groups: list) -> list[dict]:
    """Collective. ``exchange_rows`` of several groups (destination, arrays) of rows in one
    exchange; rows whose destination is this rank stay, without a message, ahead of those received.
    Only the rows that leave are sorted by rank (a step's migration moves a few of thousands)."""
    outgoing = [[None] * len(groups) for _ in range(comm.size)]
    staying = []
    for g, (destination, arrays) in enumerate(groups):
        here = destination == comm.rank
        kept = np.flatnonzero(here)   # (np.take: a third of the time of a boolean mask on rows)
        staying.append(arrays if len(kept) == len(here) else
                       {name: np.take(values, kept, axis=0) for name, values in arrays.items()})
        away = np.flatnonzero(~here & (destination >= 0))
        order = away[np.argsort(destination[away], kind="stable")]
        edges = np.searchsorted(destination[order], np.arange(comm.size + 1))
        for r in np.flatnonzero(edges[1:] > edges[:-1]):
            rows = order[edges[r]:edges[r + 1]]
            outgoing[r][g] = {name: values[rows] for name, values in arrays.items()}
    outgoing = [None if all(part is None for part in parts) else parts for parts in outgoing]
    incoming = [parts for parts in comm.alltoall(outgoing) if parts is not None]
    result = []
    for g, (_, arrays) in enumerate(groups):
        parts = [staying[g]] + [parts[g] for parts in incoming if parts[g] is not None]
        result.append({name: np.concatenate([part[name] for part in parts]) for name in arrays})
    return result


def greedy_colours(neighbours: list) -> np.ndarray:
    """(ranks,) a colour per rank, greedy in rank order, apart from every rank it lists as a
    neighbour or that lists it (``neighbours``: per rank, the ranks it holds a particle with)."""
    colour = np.zeros(len(neighbours), np.int64)
    for rank in range(len(neighbours)):
        taken = {int(colour[other]) for other in neighbours[rank] if other < rank}
        taken |= {int(colour[other]) for other in range(rank) if rank in neighbours[other]}
        colour[rank] = min(set(range(len(taken) + 1)) - taken)
    return colour


def particle_rows(particles: ParticleState, rows: np.ndarray | slice = slice(None)) -> dict:
    return {name: getattr(particles, name)[rows] for name in PARTICLE_FIELDS}


def particles_of(rows: dict) -> ParticleState:
    """A ``ParticleState`` of the rows (dict of its fields), sorted by id."""
    order = np.argsort(rows["id"], kind="stable")
    return ParticleState(**{name: np.asarray(rows[name])[order] for name in PARTICLE_FIELDS})


def gather(comm, particles: ParticleState) -> ParticleState:
    """Collective. Every rank's particles on every rank, sorted by id (for output and checkpoints)."""
    return gather_with(comm, particles)[0]


def gather_with(comm, particles: ParticleState, *arrays: np.ndarray) -> tuple:
    """Collective. ``gather``, and ``arrays`` with a row per particle gathered in the same order."""
    if comm.size == 1:
        return (particles, *arrays)
    parts = comm.allgather((particle_rows(particles), arrays))
    rows = {name: np.concatenate([part[name] for part, _ in parts]) for name in PARTICLE_FIELDS}
    order = np.argsort(rows["id"], kind="stable")
    joined = [np.concatenate([extra[k] for _, extra in parts])[order] for k in range(len(arrays))]
    return (ParticleState(**{name: values[order] for name, values in rows.items()}), *joined)


# ----------------------------------------------------------------------------------------------
# Ghost copies
# ----------------------------------------------------------------------------------------------
@dataclass
class Halo:
    """The ghost copies of one contact step on this rank (local rows: owned and ghost particles
    together, sorted by id).

    owned : (n_local,) bool; send : per neighbour rank, the local rows of owned particles it holds
    as ghosts; receive : per neighbour rank, the local rows of its particles held here;
    shared_rows : the local rows of the particles another rank holds too (owned or ghost on
    either), sorted; shared_at : per such rank, the positions in ``shared_rows`` of the particles
    both hold, by id.

    Notes
    -----
    ``to_ghosts`` copies owners' rows to their ghosts, ``to_owners`` adds the ghosts' rows to their
    owners' (and zeroes them): one message each way per neighbour, none between ranks that share
    no ghost. ``merge`` takes one message each way between ranks that hold a particle together:
    each holder sends its change to the others, and all add the changes in rank order.
    ``post_shared`` / ``take_shared`` pass the shared rows' values on from one rank to the next, in
    the order of ``colours`` (the block Gauss–Seidel's sweeps): those of the rows each rank changes
    (``passes``, agreed once per step).
    """

    comm: object
    owned: np.ndarray
    send: dict
    receive: dict
    shared_rows: np.ndarray
    shared_at: dict
    sent: int = 0          # bytes this rank has sent, the ghosts included

    @classmethod
    def build(cls, comm, partition: Partition, particles: ParticleState, width: np.ndarray | float):
        """Collective. The ghosts of every rank's ``particles`` (owned), sent to each rank whose box
        lies within ``width`` (m; per particle, or one value) of the centre. Returns the halo and
        the local particles (owned and ghosts, sorted by id)."""
        width = np.broadcast_to(np.asarray(width, float), (len(particles),))
        lower, upper = partition.lower[comm.rank], partition.upper[comm.rank]
        edge = np.minimum(particles.x - lower, upper - particles.x).min(axis=1, initial=np.inf) \
            if len(particles) else np.zeros(0)
        near = np.flatnonzero(edge < width)
        reach = partition.distance(particles.x[near]) < width[near, None]
        reach[:, comm.rank] = False
        row, rank = np.nonzero(reach)
        sources = near[row]
        holders = np.full((len(near), MAX_HOLDERS), -1, np.int32)   # every rank holding the particle
        count = reach.sum(axis=1)
        if len(near) and count.max() >= MAX_HOLDERS:
            raise RuntimeError(f"a particle is within contact range of {count.max() + 1} ranks' boxes; at most "
                               f"{MAX_HOLDERS} are supported (fewer ranks, or larger boxes)")
        holders[row, np.arange(len(row)) - np.searchsorted(row, row)] = rank
        holders[np.arange(len(near)), count] = comm.rank
        rows = {**particle_rows(particles, sources), "holders": holders[row]}
        arrived = exchange_rows(comm, rank, {**rows, "from": np.full(len(sources), comm.rank)})
        n_owned = len(particles)
        joined = {name: np.concatenate([getattr(particles, name), arrived[name]]) for name in PARTICLE_FIELDS}
        order = np.argsort(joined["id"], kind="stable")
        local = ParticleState(**{name: joined[name][order] for name in PARTICLE_FIELDS})
        where = np.empty(len(order), np.int64)
        where[order] = np.arange(len(order))                 # joined row → local row
        owned = np.zeros(len(order), bool)
        owned[where[:n_owned]] = True
        send = {int(r): where[sources[rank == r]] for r in np.unique(rank)}   # in the order sent
        ghost_rows = where[n_owned:]
        receive = {int(r): ghost_rows[arrived["from"] == r] for r in np.unique(arrived["from"])}
        # who holds what together: an owned particle with the ranks it went to, a ghost with its holders
        local_row = np.concatenate([np.repeat(where[near], MAX_HOLDERS), np.repeat(ghost_rows, MAX_HOLDERS)])
        other = np.concatenate([holders.ravel(), arrived["holders"].ravel()])
        keep = (other >= 0) & (other != comm.rank)
        local_row, other = local_row[keep], other[keep]
        pairs = np.lexsort((local_row, other))
        shared_rows = np.unique(local_row)
        shared_at = {int(r): np.searchsorted(shared_rows, local_row[pairs][other[pairs] == r])
                     for r in np.unique(other)}
        sent = sum(values.nbytes for values in rows.values())
        return cls(comm, owned, send, receive, shared_rows, shared_at, sent), local

    def _swap(self, outgoing: dict, incoming: dict, array: np.ndarray, combine) -> None:
        """Send array[outgoing[r]] to each r; each received block goes to array[incoming[r]] by ``combine``."""
        shape = array.shape[1:]
        requests, buffers = [], {}
        for r, rows in incoming.items():
            buffers[r] = np.empty((len(rows),) + shape, array.dtype)
            requests.append(self.comm.Irecv(buffers[r], source=r, tag=77))
        blocks = [np.ascontiguousarray(array[rows]) for rows in outgoing.values()]
        requests += [self.comm.Isend(block, dest=r, tag=77) for r, block in zip(outgoing, blocks)]
        self.sent += sum(block.nbytes for block in blocks)
        MPI.Request.Waitall(requests)
        for r, rows in incoming.items():
            combine(array, rows, buffers[r])

    def to_ghosts(self, *arrays: np.ndarray) -> None:
        """Collective. Each ghost row takes its owner's value, in place."""
        for array in arrays:
            self._swap(self.send, self.receive, array, _assign)

    def to_owners(self, *arrays: np.ndarray) -> None:
        """Collective. Each ghost row is added to its owner's row and set to zero, in place."""
        for array in arrays:
            self._swap(self.receive, self.send, array, _add)
            for rows in self.receive.values():
                array[rows] = 0

    def sum_over_holders(self, array: np.ndarray) -> np.ndarray:
        """Collective. ``array`` (a row per local particle) with each row the sum of the rows of every
        rank that holds the particle, on each of them (ghosts added to their owner, then copied back)."""
        self.to_owners(array)
        self.to_ghosts(array)
        return array

    def max_over_holders(self, array: np.ndarray) -> np.ndarray:
        """Collective. As ``sum_over_holders``, the largest instead of the sum."""
        self._swap(self.receive, self.send, array, _maximum)
        self.to_ghosts(array)
        return array

    def colours(self) -> np.ndarray:
        """Collective. (comm.size,) a colour per rank, ranks holding a particle together coloured
        apart (``greedy_colours``; two ranks: 0 and 1), the same on every rank."""
        return greedy_colours(self.comm.allgather(sorted(self.shared_at)))

    def passes(self, ranks, changing: np.ndarray) -> dict:
        """Collective among ``ranks`` (those this rank shares particles with). Per rank r of them,
        (the local rows this rank passes on to r, those r passes on here): of the particles both
        hold, those ``changing`` (bool per local row) here, and there (one message each way)."""
        rows = {r: self.shared_rows[self.shared_at[r]] for r in ranks}
        masks = {r: changing[rows[r]].astype(np.uint8) for r in ranks}
        theirs = {r: np.empty_like(mask) for r, mask in masks.items()}
        requests = [self.comm.Irecv(theirs[r], source=r, tag=80) for r in ranks]
        requests += [self.comm.Isend(masks[r], dest=r, tag=80) for r in ranks]
        MPI.Request.Waitall(requests)
        return {r: (rows[r][masks[r] > 0], rows[r][theirs[r] > 0]) for r in ranks}

    def post_shared(self, passes: dict, ranks, *arrays: np.ndarray) -> list:
        """Send each of ``ranks`` the rows of ``arrays`` (2-D) it is passed (``passes``), side by
        side, without waiting; returns (request, buffer) pairs: wait on the requests before the buffers go."""
        requests = []
        for r in ranks:
            block = _rows_of(passes[r][0], arrays)
            self.sent += block.nbytes
            requests.append((self.comm.Isend(block, dest=r, tag=79), block))
        return requests

    def take_shared(self, passes: dict, ranks, *arrays: np.ndarray) -> None:
        """Receive from each of ``ranks``, in that order, what its ``post_shared`` sent, and set the
        rows it passes here (``passes``) to it (the later rank's value where two send one)."""
        width = sum(array.shape[1] for array in arrays)
        for r in ranks:
            rows = passes[r][1]
            block = np.empty((len(rows), width))
            self.comm.Recv(block, source=r, tag=79)
            _set_rows(rows, block, arrays)

    def merge(self, reference: tuple, *arrays: np.ndarray) -> None:
        """Collective. Copies of particles changed by the ranks that hold them: each holder's change
        since ``reference`` (the arrays as they were at the last merge, the same on every holder) is
        sent to the other holders, and every holder sets reference + the changes of all, added in
        rank order (so the copies stay equal to the bit); the reference arrays' shared rows take the
        merged values. Rows held here only are left as they are, in both. It touches the shared rows
        only (the warm start of the block Gauss–Seidel: each rank's remembered impulses summed)."""
        rows = self.shared_rows
        if len(rows) == 0:
            return
        arrays, reference = tuple(arrays), tuple(reference)
        if not all(a.ndim == 2 and a.flags.c_contiguous for a in arrays + reference):
            raise ValueError("Halo.merge takes C-contiguous 2-D arrays")
        change = _rows_of(rows, arrays) - _rows_of(rows, reference)
        # the other holders' changes in one buffer, in rank order (the lower ranks' rows first)
        neighbours = sorted(self.shared_at)
        at = [self.shared_at[r] for r in neighbours]
        edges = np.cumsum([0] + [len(positions) for positions in at])
        received = np.empty((edges[-1], change.shape[1]))
        requests = [self.comm.Irecv(received[edges[k]:edges[k + 1]], source=r, tag=78)
                    for k, r in enumerate(neighbours)]
        # a neighbour holding every shared row (two ranks: always) takes the changes as they are
        outgoing = [change if len(positions) == len(rows) else np.ascontiguousarray(change[positions])
                    for positions in at]
        requests += [self.comm.Isend(block, dest=r, tag=78) for r, block in zip(neighbours, outgoing)]
        self.sent += sum(block.nbytes for block in outgoing)
        MPI.Request.Waitall(requests)
        below = int(edges[np.searchsorted(neighbours, self.comm.rank)])
        positions = np.concatenate([np.zeros(0, np.int64), *at])
        _apply_merged(rows, arrays, reference, change, received, positions, below)


@njit(cache=True)
def _rows_of(rows, arrays):
    """(len(rows), Σ widths): the arrays' ``rows`` side by side."""
    width = 0
    for k in range(len(arrays)):
        width += arrays[k].shape[1]
    out = np.empty((len(rows), width))
    column = 0
    for k in range(len(arrays)):
        for i in range(len(rows)):
            for j in range(arrays[k].shape[1]):
                out[i, column + j] = arrays[k][rows[i], j]
        column += arrays[k].shape[1]
    return out


@njit(cache=True)
def _set_rows(rows, block, arrays):
    """The inverse of ``_rows_of``: the arrays' ``rows`` set to ``block``'s columns."""
    column = 0
    for k in range(len(arrays)):
        for i in range(len(rows)):
            for j in range(arrays[k].shape[1]):
                arrays[k][rows[i], j] = block[i, column + j]
        column += arrays[k].shape[1]


@njit(cache=True)
def _apply_merged(rows, arrays, reference, change, received, at, below):
    """Each array and its reference set, on ``rows``, to reference + the sum of every holder's
    change. The sum is taken in rank order, so that every holder gets the same bits: the
    ``received`` rows (at positions ``at`` of ``rows``) of lower ranks (the first ``below``), this
    rank's ``change``, then the higher ranks'."""
    total = np.zeros_like(change)
    width = change.shape[1]
    for i in range(below):
        for j in range(width):
            total[at[i], j] += received[i, j]
    for i in range(len(change)):
        for j in range(width):
            total[i, j] += change[i, j]
    for i in range(below, len(at)):
        for j in range(width):
            total[at[i], j] += received[i, j]
    column = 0
    for k in range(len(arrays)):
        now, before = arrays[k], reference[k]
        for i in range(len(rows)):
            r = rows[i]
            for j in range(now.shape[1]):
                now[r, j] = before[r, j] = before[r, j] + total[i, column + j]
        column += now.shape[1]


def _assign(array, rows, values):
    array[rows] = values


def _maximum(array, rows, values):
    array[rows] = np.maximum(array[rows], values)


def _add(array, rows, values):
    array[rows] += values   # (a rank's rows are distinct: no np.add.at needed)
