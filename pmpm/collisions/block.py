"""The block Gauss–Seidel's sweeps over the ranks, compiled with their messages: one call a dense
step, as one rank's ``impulses.sweep`` (``subdomains.block_sweeps`` prepares the blocks and says
what a sweep over the ranks is)."""
from __future__ import annotations

import numpy as np
from numba import njit

from .impulses import change_since, conjugate_step, sweep_from
from .messages import clock, post, post_maximum, receive, requests, statuses, wait, wait_all

SWEEP_TAG, AFTER_TAG = 79, 76
TESTS = 3   # the stopping tests in flight at once, at most (two, and the one being posted)


@njit(cache=True)
def sweeps(border, inner, watched, arm, contacts, bodies, lam_n, lam_t, neighbours, n_lower, passed, budget,
           tol, mpi):
    """Sweeps of this rank's contacts until no watched body's contact-point velocity changed by more
    than ``tol`` (m/s) in a sweep on any rank, or ``budget`` sweeps; returns the sweeps made (the
    same on every rank) and the seconds this rank waited for the others' messages (bench/rank_waits.py).
    Updates ``lam_n``, ``lam_t`` and the bodies' v, ω in place.

    border, inner : (rows, 1/k_n, 1/k_t) of the contacts touching a shared particle, and of the others
    watched, arm : the bodies the stopping test watches, and every body's arm (``impulses.watched_bodies``)
    contacts : (first, second, normal, r_first, r_second, u_wall, target, μ); bodies : (1/m, 1/I, v, ω)
    neighbours : the ranks sharing particles with this one, in colour order; the first ``n_lower``
        have lower colours than this rank
    passed : (sweep rows, their offsets per neighbour, rows sent after the last sweep, offsets,
        rows received then, offsets): local rows of the shared particles (``halo.Halo.passes``)
    mpi : ``messages.handles`` of the communicator
    """
    first, second, normal, r_first, r_second, u_wall, target, mu = contacts
    inv_m, inv_i, v, w = bodies
    swept, swept_at, sent_after, sent_at, received_after, received_at = passed
    stepped = (first, second, normal, r_first, r_second, inv_m, inv_i, v, w, lam_n, lam_t)
    # each block's impulses before a sweep and its conjugate direction
    border_before, border_direction = np.empty((len(border[0]), 4)), np.zeros((len(border[0]), 4))
    inner_before, inner_direction = np.empty((len(inner[0]), 4)), np.zeros((len(inner[0]), 4))
    count = len(neighbours)
    outgoing, incoming = np.empty((len(swept), 6)), np.empty((len(swept), 6))
    held, status = requests(count + TESTS, mpi), statuses(count, mpi)
    largest, reduced = np.zeros(TESTS), np.zeros(TESTS)
    saved = np.empty((len(watched), 6))
    change_since(watched, v, w, arm, saved)   # (saved takes their velocities)
    conjugate_step(inner[0], 2.0, inner_before, inner_direction, *stepped, True)   # (β = 2: none; p = 0)
    # A rank with lower colours among its neighbours sweeps the first half of its inner contacts
    # before its border: work in hand while they sweep theirs, as the lowest colour has its inner
    # sweep while the others sweep their border. With its border first, it would end each sweep just
    # as the lower colours' next copies are due, and wait for every stall of theirs at once. A send
    # is waited on only before its buffer takes the next sweep's copies.
    half = len(inner[0]) // 2 if n_lower > 0 else 0
    early = (inner[0][:half], inner[1][:half], inner[2][:half], inner_before[:half])
    late = (inner[0][half:], inner[1][half:], inner[2][half:], inner_before[half:])
    done, previous, beta, stop = 0, 0.0, 2.0, False
    oldest, in_flight = 0, 0   # the stopping tests being reduced: slots oldest, oldest + 1, ... (mod TESTS)
    waited = 0.0
    while not stop:
        # the inner sweep's first half (on a rank with lower colours), the border's conjugate step (of
        # the sweep before) and sweep after the lower colours', then the rest of the inner sweep and
        # the inner conjugate step (no other rank's body) while the higher colours sweep their border
        size = sweep_from(*early, first, second, normal, r_first, r_second, u_wall, target, mu, inv_m, inv_i, v, w,
                          lam_n, lam_t)
        start = clock()
        for k in range(n_lower):
            _take(swept[swept_at[k]:swept_at[k + 1]], incoming[swept_at[k]:swept_at[k + 1]], neighbours[k],
                  SWEEP_TAG, v, w, status, mpi)
        waited += clock() - start
        conjugate_step(border[0], beta, border_before, border_direction, *stepped, True)
        size += sweep_from(border[0], border[1], border[2], border_before, first, second, normal, r_first, r_second,
                           u_wall, target, mu, inv_m, inv_i, v, w, lam_n, lam_t)
        start = clock()
        if done > 0:   # the copies of the sweep before have left the buffer
            wait_all(held, count, status, mpi)
        waited += clock() - start
        for k in range(count):
            _post(swept[swept_at[k]:swept_at[k + 1]], outgoing[swept_at[k]:swept_at[k + 1]], neighbours[k],
                  SWEEP_TAG, v, w, held, k, mpi)
        size += sweep_from(*late, first, second, normal, r_first, r_second, u_wall, target, mu, inv_m, inv_i, v, w,
                           lam_n, lam_t)
        done += 1
        if in_flight == 2:   # the test of the sweep before the last, reduced meanwhile
            start = clock()
            wait(held, count + oldest, status, mpi)
            waited += clock() - start
            stop = reduced[oldest] <= tol
            oldest, in_flight = (oldest + 1) % TESTS, in_flight - 1
        stop = stop or done == budget
        beta = size / previous if previous > 0 else 2.0
        previous = size
        if not stop:
            conjugate_step(inner[0], beta, inner_before, inner_direction, *stepped, True)
        start = clock()
        for k in range(n_lower, count):
            _take(swept[swept_at[k]:swept_at[k + 1]], incoming[swept_at[k]:swept_at[k + 1]], neighbours[k],
                  SWEEP_TAG, v, w, status, mpi)
        waited += clock() - start
        slot = (oldest + in_flight) % TESTS
        largest[slot] = change_since(watched, v, w, arm, saved)
        post_maximum(largest[slot:slot + 1], reduced[slot:slot + 1], held, count + slot, mpi)
        in_flight += 1
    start = clock()
    wait_all(held, count, status, mpi)
    for _ in range(in_flight):
        wait(held, count + oldest, status, mpi)
        oldest = (oldest + 1) % TESTS
    # the rows only the sender changed, once: every holder then has every shared row as if all had
    # been passed each sweep
    outgoing, incoming = np.empty((len(sent_after), 6)), np.empty((len(received_after), 6))
    for k in range(count):
        _post(sent_after[sent_at[k]:sent_at[k + 1]], outgoing[sent_at[k]:sent_at[k + 1]], neighbours[k], AFTER_TAG,
              v, w, held, k, mpi)
    for k in range(count):
        _take(received_after[received_at[k]:received_at[k + 1]], incoming[received_at[k]:received_at[k + 1]],
              neighbours[k], AFTER_TAG, v, w, status, mpi)
    wait_all(held, count, status, mpi)
    return done, waited + clock() - start


@njit(cache=True)
def _post(rows, block, to, tag, v, w, held, k, mpi):
    """Send rank ``to`` the (v, ω) of ``rows`` (packed in ``block``, (len(rows), 6))."""
    for i in range(len(rows)):
        for d in range(3):
            block[i, d], block[i, 3 + d] = v[rows[i], d], w[rows[i], d]
    post(block, to, tag, held, k, mpi)


@njit(cache=True)
def _take(rows, block, source, tag, v, w, status, mpi):
    """Receive (v, ω) of ``rows`` from rank ``source`` (into ``block``, (len(rows), 6)) and set them."""
    receive(block, source, tag, status, mpi)
    for i in range(len(rows)):
        for d in range(3):
            v[rows[i], d], w[rows[i], d] = block[i, d], block[i, 3 + d]
