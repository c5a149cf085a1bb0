"""How often this machine stops a core: each process spins reading the clock and adds up the gaps.

    .venv/bin/python bench/cpu_gaps.py [SECONDS] [--cores 0,1] [--gap-us 20]

One process per core in ``--cores`` (pinned, all at once; then the first core alone) reads a
monotonic clock in a compiled loop for SECONDS (default 20) and counts every gap between two
readings longer than ``--gap-us`` microseconds: the time the core ran something else (an interrupt,
the kernel, another process, or, in a virtual machine, the host). Printed per core: the gaps, the
share of the time lost, and how that time splits by the gaps' length.

Why it matters to pmpm: ranks that exchange messages every fraction of a millisecond (the block
sweeps' 20 messages a contact step) wait for each other's stops, so a run on several ranks loses
the stops of every core it uses, where one rank loses its own only (docs/collisions.md, "Speed on
2 ranks").
"""
import argparse
import ctypes
import os
import sys
from multiprocessing import Process, Queue

import numpy as np
from numba import njit

EDGES_US = (100, 1000, 3000, 10000, 30000)   # the gaps' length classes, µs

_libc = ctypes.CDLL(None)
_clock_gettime = _libc.clock_gettime
_clock_gettime.argtypes = (ctypes.c_int, ctypes.c_void_p)


@njit(cache=True)
def _spin(clock, timespec, seconds, gap, edges):
    """Read the clock for ``seconds``; returns the gaps longer than ``gap`` (s) and their time per
    length class (``edges``, s: the classes below each edge, then above the last)."""
    lost = np.zeros(len(edges) + 1)
    count = 0
    clock(1, timespec.ctypes.data)            # CLOCK_MONOTONIC
    start = last = timespec[0] + 1e-9 * timespec[1]
    while last - start < seconds:
        clock(1, timespec.ctypes.data)
        now = timespec[0] + 1e-9 * timespec[1]
        if now - last > gap:
            count += 1
            k = 0
            while k < len(edges) and now - last >= edges[k]:
                k += 1
            lost[k] += now - last
        last = now
    return count, lost


def spin_on(core: int, seconds: float, gap_us: float, results: Queue) -> None:
    os.sched_setaffinity(0, {core})
    timespec = np.zeros(2, np.int64)
    count, lost = _spin(_clock_gettime, timespec, seconds, gap_us * 1e-6, np.array(EDGES_US) * 1e-6)
    results.put((core, count, lost))


def measure(cores, seconds: float, gap_us: float) -> list:
    results = Queue()
    workers = [Process(target=spin_on, args=(core, seconds, gap_us, results)) for core in cores]
    for worker in workers:
        worker.start()
    rows = sorted(results.get() for _ in workers)
    for worker in workers:
        worker.join()
    return rows


def report(label: str, rows: list, seconds: float, gap_us: float) -> None:
    classes = [f"<{EDGES_US[0] / 1000:g} ms"] + [f"{a / 1000:g}-{b / 1000:g} ms" for a, b in zip(EDGES_US, EDGES_US[1:])] \
        + [f">{EDGES_US[-1] / 1000:g} ms"]
    for core, count, lost in rows:
        print(f"{label}: core {core}: {count} gaps over {gap_us:g} us in {seconds:g} s, {lost.sum():.3f} s lost "
              f"({100 * lost.sum() / seconds:.2f} %); by length "
              + ", ".join(f"{name} {value:.3f} s" for name, value in zip(classes, lost)), flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seconds", nargs="?", type=float, default=20.0)
    parser.add_argument("--cores", default="0,1")
    parser.add_argument("--gap-us", type=float, default=20.0)
    args = parser.parse_args()
    cores = [int(c) for c in args.cores.split(",")]
    _spin(_clock_gettime, np.zeros(2, np.int64), 0.01, 1.0, np.array(EDGES_US) * 1e-6)   # compiled once, here
    report("all busy", measure(cores, args.seconds, args.gap_us), args.seconds, args.gap_us)
    report("alone", measure(cores[:1], args.seconds, args.gap_us), args.seconds, args.gap_us)


if __name__ == "__main__":
    sys.exit(main())
