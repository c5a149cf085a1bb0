"""How the particle exchange of ranks owning particles scales: measured geometry, modelled time.

    OMP_NUM_THREADS=1 .venv/bin/python bench/ownership_scaling.py [N] [--ranks 2,8,64,256]
        [--compute US] [--latency US] [--bandwidth GBS] [--sweeps K]

The bed of ``bench/contacts.py`` (N spheres, default 100,000, on a lattice 1 % apart in a box) is
cut into P boxes by ``ownership.bisect`` (in one process: the bisection's reductions over ranks are
sums of histograms, the same whole), and for each box the ghosts a contact step copies in
(a dense step's rule: within r + r_max + two travels of the box) and the particles it shares (the rows of
its sweeps' messages) are counted, and the ranks coloured as the block Gauss–Seidel colours them
(greedy, two ranks sharing a particle apart). The bed's contacts are its lattice neighbours (centres
within 2.04 r), each solved by the owner of its lower-id sphere; a sweep's message from one rank to
another carries the shared particles both ranks' contacts change, the rows only the sender changes
go once after the last sweep (``halo.Halo.passes``). Printed per P: the most owned and ghost
particles of a rank, its shared particles and the rows of its sweeps' messages, the bytes a rank
sends per step (ghosts once, 170 B each; 48 B a row: every shared particle for the warm start, the
sweep rows after each of the K sweeps, the rest once), the neighbours it exchanges with, the
colours, and a time per step

    t(P) = max(compute × (owned + ghosts), K × C × border) + (K + 2) × neighbours × latency
           + bytes of the messages / bandwidth + K × (C − 1) × latency + 6 × log2(P) × latency

A sweep passes the shared particles' copies from colour to colour: the C colours' border contacts
(those touching a shared particle) are swept one colour after another, each while the others sweep
their inner contacts, so a step takes at least K × C × border (border: a sweep of a rank's border
contacts, taken as the sweeps' share of the compute, 40 %, / K per shared particle) and the chain's
latencies (compute: µs per particle and step of the engine on one rank, measured by ``bench/contacts.py``;
latency, bandwidth: of the network, given; the last term: the step's reductions).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from contacts import bed_lattice  # noqa: E402
from pmpm.ownership import bisect, greedy_colours  # noqa: E402

SWEEP_SHARE = 0.4   # the sweeps' share of a dense step's compute (bench/hopper.py's profile, 1 rank: 10 of 25 s)


class WholeComm:
    """A communicator of ``size`` ranks whose only process holds every particle: reductions are the
    values themselves (what ``bisect`` needs)."""

    def __init__(self, size):
        self.size, self.rank = size, 0

    def Allreduce(self, send, receive=None, op=None):
        pass


def option(name, default):
    return type(default)(sys.argv[sys.argv.index(name) + 1]) if name in sys.argv else default


def main():
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    values = {sys.argv[i + 1] for i, a in enumerate(sys.argv) if a.startswith("--") and i + 1 < len(sys.argv)}
    args = [a for a in args if a not in values]
    n = int(args[0]) if args else 100_000
    ranks = [int(p) for p in option("--ranks", "2,8,64,256").split(",")]
    compute, latency, bandwidth, sweeps = (option("--compute", 5.0), option("--latency", 2.0),
                                           option("--bandwidth", 5.0), option("--sweeps", 20))
    state, _, _, dt = bed_lattice(n)
    r = float(state.radius.max())
    # a dense step's ghosts: within r + r_max + the particle's travel + the fastest travel, every
    # particle at 1 m/s (a settling bed is slower; subdomains.advance_owned)
    width = state.radius + r + 2 * 1.0 * dt
    print(f"{n} spheres (r = {r} m), bed {np.ptp(state.x, axis=0).round(3)} m; compute {compute} µs/particle/step, "
          f"latency {latency} µs, bandwidth {bandwidth} GB/s, {sweeps} sweeps")
    contacts = cKDTree(state.x).query_pairs(2.04 * r, output_type="ndarray")   # ids: the rows (i < j)
    print(f"{len(contacts)} contacts (lattice neighbours)")
    print(f"{'ranks':>6s} {'owned':>8s} {'ghosts':>8s} {'shared':>8s} {'rows/sweep':>10s} {'neighbours':>10s} "
          f"{'colours':>7s} {'kB/step':>9s} {'B/owned':>8s} {'model ms/step':>14s} {'speed-up':>9s}")
    one = compute * n / 1000
    for p in ranks:
        partition = bisect(WholeComm(p), state.x)
        owner = partition.owner_of(state.x)
        reaches = np.concatenate([partition.distance(state.x[k:k + 5000]) < width[k:k + 5000, None]
                                  for k in range(0, n, 5000)])
        reaches &= np.arange(p)[None] != owner[:, None]   # ghost copies
        owned = np.bincount(owner, minlength=p)
        ghosts = reaches.sum(axis=0)
        held = reaches | (np.arange(p)[None] == owner[:, None])
        shared_rows = (held & (held.sum(axis=1) > 1)[:, None]).sum(axis=0)
        # neighbours: ranks that hold a particle together
        shared = held[held.sum(axis=1) > 1].astype(int)
        together = (shared.T @ shared) > 0
        np.fill_diagonal(together, False)
        neighbours = int(together.sum(axis=1).max())
        colours = colouring(together)
        sweep_rows, rest_rows = message_rows(held, owner[contacts.min(axis=1)], contacts, p)
        worst = int(np.argmax(owned + ghosts))
        ghost_bytes = 170 * ghosts[worst]   # a ghost's row: the particle's 98 B, its 16 holders, its row
        message_bytes = 48 * (shared_rows[worst] + sweeps * sweep_rows[worst] + rest_rows[worst])
        sent = ghost_bytes + message_bytes
        border = SWEEP_SHARE * compute / sweeps * shared_rows.max()
        t = (max(compute * (owned[worst] + ghosts[worst]), sweeps * colours * border)
             + (sweeps + 2) * neighbours * latency + message_bytes / (bandwidth * 1e3)
             + sweeps * (colours - 1) * latency + 6 * math.log2(p) * latency) / 1000
        print(f"{p:6d} {owned.max():8d} {ghosts.max():8d} {shared_rows.max():8d} {sweep_rows.max():10d} "
              f"{neighbours:10d} {colours:7d} {sent / 1e3:9.1f} {sent / owned[worst]:8.0f} {t:14.2f} {one / t:9.1f}",
              flush=True)


def message_rows(held: np.ndarray, solver: np.ndarray, contacts: np.ndarray, p: int) -> tuple:
    """Per rank, the rows its sweeps' messages carry (to all its neighbours together) and the rows
    it sends once after the last sweep: of the particles it shares with a neighbour, those both
    ranks' contacts change, and those only its own do. ``held`` (n, P) bool; ``solver`` the rank
    solving each of ``contacts`` (k, 2)."""
    n = len(held)
    ends = np.concatenate([contacts[:, 0], contacts[:, 1]])
    changes = scipy.sparse.csr_matrix((np.ones(len(ends)), (ends, np.concatenate([solver, solver]))), shape=(n, p))
    changes.data[:] = 1.0                                   # (duplicates summed: a particle changed by a rank)
    holding = scipy.sparse.csr_matrix(held.astype(float))
    changing = holding.multiply(changes).tocsr()            # held and changed there
    both = (changing.T @ changing).toarray()                # [a, b]: shared rows both change
    only = (changing.T @ holding).toarray() - both          # [a, b]: rows a changes, b holds, b does not change
    np.fill_diagonal(both, 0.0)
    np.fill_diagonal(only, 0.0)
    return both.sum(axis=1).astype(int), only.sum(axis=1).astype(int)


def colouring(together: np.ndarray) -> int:
    """How many colours ``pmpm.halo.Halo.colours`` gives the ranks' graph (``together``: (P, P) bool)."""
    return int(greedy_colours([np.flatnonzero(row).tolist() for row in together]).max()) + 1


if __name__ == "__main__":
    main()
