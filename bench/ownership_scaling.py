"""How the particle exchange of ranks owning particles scales: measured geometry, modelled time.

    OMP_NUM_THREADS=1 .venv/bin/python bench/ownership_scaling.py [N] [--ranks 2,8,64,256]
        [--compute US] [--latency US] [--bandwidth GBS] [--sweeps K]

The bed of ``bench/contacts.py`` (N spheres, default 100,000, on a lattice 1 % apart in a box) is
cut into P boxes by ``ownership.bisect`` (in one process: the bisection's reductions over ranks are
sums of histograms, the same whole), and for each box the ghosts a contact step copies in
(a dense step's rule: within r + r_max + two travels of the box) and the particles it shares (the rows of
its merge per round of sweeps) are counted. Printed per P: the most owned and ghost particles of a
rank, the bytes a rank sends per step (ghosts once, 170 B each; 48 B per shared particle per merge,
M + 1 merges: M = K / LOCAL_SWEEPS rounds of K sweeps, and the warm start's),
the neighbours it exchanges with, and a time per step

    t(P) = compute × (owned + ghosts) + (M + 1) × (neighbours × latency + bytes per merge / bandwidth)
           + 6 × log2(P) × latency

(compute: µs per particle and step of the engine on one rank, measured by ``bench/contacts.py``;
latency, bandwidth: of the network, given; the last term: the step's reductions).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from contacts import bed_lattice  # noqa: E402
from pmpm.collisions.settings import LOCAL_SWEEPS  # noqa: E402
from pmpm.ownership import bisect  # noqa: E402


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
    print(f"{'ranks':>6s} {'owned':>8s} {'ghosts':>8s} {'shared':>8s} {'neighbours':>10s} {'kB/step':>9s} "
          f"{'B/owned':>8s} {'model ms/step':>14s} {'speed-up':>9s}")
    one = compute * n / 1000
    merges = math.ceil(sweeps / LOCAL_SWEEPS)
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
        shared = held[held.sum(axis=1) > 1]
        neighbours = max(int(((shared.T.astype(int) @ shared.astype(int)) > 0).sum(axis=1).max() - 1), 0) \
            if len(shared) else 0
        worst = int(np.argmax(owned + ghosts))
        ghost_bytes = 170 * ghosts[worst]   # a ghost's row: the particle's 98 B, its 16 holders, its row
        merge_bytes = 48 * shared_rows[worst]
        sent = ghost_bytes + (merges + 1) * merge_bytes
        t = (compute * (owned[worst] + ghosts[worst]) + (merges + 1) * (neighbours * latency + merge_bytes / (bandwidth * 1e3))
             + 6 * math.log2(p) * latency) / 1000
        print(f"{p:6d} {owned.max():8d} {ghosts.max():8d} {shared_rows.max():8d} {neighbours:10d} {sent / 1e3:9.1f} "
              f"{sent / owned[worst]:8.0f} {t:14.2f} {one / t:9.1f}", flush=True)


if __name__ == "__main__":
    main()
