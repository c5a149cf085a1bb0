"""Particle rows packed into one block, merged by id, and exchanged between ranks (``pmpm.packed``)."""
import numpy as np
import pytest

from pmpm.packed import exchanged, gathered, merged, packed
from pmpm.particles import ParticleState


def random_particles(rng, ids) -> ParticleState:
    n = len(ids)
    return ParticleState(np.asarray(ids, np.int64), rng.random((n, 3)), rng.random((n, 3)), rng.random((n, 3)),
                         rng.random(n), rng.random(n), rng.integers(0, 3, n).astype(np.int8), rng.random(n) < 0.5)


def test_packed_rows_merge_by_id_as_a_sort_would():
    """200 particles (even ids, some dropped) and 9 arrived rows (odd ids and ids past the last, any
    order) with two (n, 3) arrays each: the merged state, its arrays and the rows' places are those
    of concatenating and sorting; rows packed and merged into no particles are the particles' rows,
    bit for bit (ids beyond 2^31 too)."""
    rng = np.random.default_rng(3)
    own = random_particles(rng, 2 * np.arange(200) + 2 ** 40)
    force, torque = rng.random((200, 3)), rng.random((200, 3))
    arriving = random_particles(rng, np.array([1, 401, 7, 999, 3, 55, 1001, 397, 2001]) + 2 ** 40)
    extra_force, extra_torque = rng.random((9, 3)), rng.random((9, 3))
    block = packed(arriving, np.arange(9), extra_force, extra_torque)
    keep = rng.random(200) > 0.1
    state, where_own, where_block, (f, t) = merged(own, block, keep, (force, torque))
    ids = np.concatenate([own.id[keep], arriving.id])
    order = np.argsort(ids)
    np.testing.assert_array_equal(state.id, ids[order])
    for name in ("x", "v", "omega", "radius", "density", "motion", "deposited"):
        joined = np.concatenate([getattr(own, name)[keep], getattr(arriving, name)])
        np.testing.assert_array_equal(getattr(state, name), joined[order])
        assert getattr(state, name).dtype == getattr(own, name).dtype
    np.testing.assert_array_equal(f, np.concatenate([force[keep], extra_force])[order])
    np.testing.assert_array_equal(t, np.concatenate([torque[keep], extra_torque])[order])
    np.testing.assert_array_equal(state.id[where_own[keep]], own.id[keep])
    assert (where_own[~keep] == -1).all()
    np.testing.assert_array_equal(state.id[where_block], arriving.id)
    back = merged(ParticleState.empty(), packed(own, np.array([5, 0, 199])))[0]   # (sorted by id)
    for name in ("id", "x", "v", "omega", "radius", "density", "motion", "deposited"):
        np.testing.assert_array_equal(getattr(back, name), getattr(own, name)[[0, 5, 199]])


def test_members_of_a_sorted_set_are_those_isin_finds():
    """``arrays.members`` against np.isin: values below, between, on and past the set's ends,
    repeated, an empty set and no values."""
    from pmpm.arrays import members
    rng = np.random.default_rng(5)
    ascending = np.unique(rng.integers(10, 90, 30))
    values = rng.integers(0, 100, 400)
    np.testing.assert_array_equal(members(values, ascending), np.isin(values, ascending))
    assert not members(values, ascending[:0]).any()
    assert members(ascending[:0], ascending).shape == (0,)


@pytest.mark.mpi
def test_rows_reach_the_ranks_they_are_sent_to(comm):
    """Each rank sends rows to every rank, itself included (r + 1 rows to rank r, in no order, and
    two rows to nowhere, −1; two groups of different widths in one exchange of counts): each
    receives them in rank order, with offsets, and none of those sent nowhere."""
    size, rank = comm.size, comm.rank
    rows = np.append(np.repeat(np.arange(size), np.arange(1, size + 1)), [-1, -1])
    destination = np.random.default_rng(rank).permutation(rows)
    wide = np.stack([np.full(len(destination), rank), destination, np.arange(len(destination))], axis=1).astype(float)
    narrow = wide[:, :1] + 0.5
    (got, offsets), (got_narrow, narrow_offsets) = exchanged(comm, (destination, wide), (destination, narrow))
    expected_from = np.repeat(np.arange(size), rank + 1)
    np.testing.assert_array_equal(offsets, np.arange(size + 1) * (rank + 1))
    np.testing.assert_array_equal(narrow_offsets, offsets)
    np.testing.assert_array_equal(got[:, 0], expected_from)
    assert (got[:, 1] == rank).all()
    every = comm.allgather(destination)
    for r in range(size):   # each sender's rows, in the order it sent them
        np.testing.assert_array_equal(got[offsets[r]:offsets[r + 1], 2], np.flatnonzero(every[r] == rank))
    np.testing.assert_array_equal(got_narrow[:, 0], expected_from + 0.5)


@pytest.mark.mpi
def test_every_rank_gets_every_ranks_rows_in_rank_order(comm):
    """Rank r gathers r rows of width 3 and 2r + 1 of width 1 (rank 0: none of the first): every
    rank receives them all, rank 0's first, each rank's in its order."""
    rank = comm.rank
    wide = np.column_stack([np.full(rank, rank), np.arange(rank), -np.arange(rank)]).astype(float)
    narrow = np.arange(2 * rank + 1, dtype=float)[:, None] + 100 * rank
    got_wide, got_narrow = gathered(comm, wide, narrow)
    every = range(comm.size)
    np.testing.assert_array_equal(got_wide[:, 0], np.concatenate([np.full(r, r) for r in every]))
    np.testing.assert_array_equal(got_wide[:, 1], np.concatenate([np.arange(r) for r in every]))
    np.testing.assert_array_equal(got_wide[:, 2], -got_wide[:, 1])
    np.testing.assert_array_equal(got_narrow[:, 0], np.concatenate([np.arange(2 * r + 1) + 100 * r for r in every]))


@pytest.mark.mpi
def test_the_kernels_own_messages_reach_every_rank(comm):
    """The MPI calls the compiled kernels make themselves (``collisions.messages``, the block sweeps'
    messages): rows sent to the next rank without waiting arrive there whole, from the rank before,
    and the nonblocking maximum is the largest value of every rank."""
    from pmpm.collisions import messages
    size, rank = comm.size, comm.rank
    mpi = messages.handles(comm)
    held, status = messages.requests(2, mpi), messages.statuses(1, mpi)
    rows = np.arange(12.0).reshape(4, 3) + 100 * rank
    messages.post(rows, (rank + 1) % size, 5, held, 0, mpi)
    got = np.empty_like(rows)
    messages.receive(got, (rank - 1) % size, 5, status, mpi)
    messages.wait_all(held, 1, status, mpi)
    np.testing.assert_array_equal(got, np.arange(12.0).reshape(4, 3) + 100 * ((rank - 1) % size))
    value, largest = np.array([rank + 0.5]), np.zeros(1)
    messages.post_maximum(value, largest, held, 1, mpi)
    messages.wait(held, 1, status, mpi)
    assert largest[0] == size - 0.5
