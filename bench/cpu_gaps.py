"""How often this machine stops a core, and how its cores' pace varies: what ranks in step lose.

    .venv/bin/python bench/cpu_gaps.py [SECONDS] [--cores 0,1] [--gap-us 20] [--window-ms 30] [--pace-only]

One process per core in ``--cores`` (pinned, all at once; then the first core alone) reads a
monotonic clock in a compiled loop for SECONDS (default 20) and counts every gap between two
readings longer than ``--gap-us`` microseconds: the time the core ran something else (an interrupt,
the kernel, another process, or, in a virtual machine, the host). Printed per core: the gaps, the
share of the time lost, and how that time splits by the gaps' length.

Then the pace: one process per core (all at once; then the first core alone) repeats a fixed
compiled piece of work (sums over an array read in a scattered order, as the contact sweeps read
their bodies; about 3 ms a piece) for SECONDS and clocks each piece. Printed per core: how much slower than its fastest tenth
it ran on average, and the share of ``--window-ms`` windows in which it ran 1.2 × slower or more;
then what cores in step lose: over the same windows, the work of the slower core of each window
against the mean of the cores' (ranks that wait for each other at every exchange advance at the
slower one's pace; one rank at its own).

Why it matters to pmpm: ranks that exchange messages every fraction of a millisecond (the block
sweeps' 20 messages a contact step) wait for each other's stops and slow spells, so a run on
several ranks loses those of every core it uses, where one rank loses its own only
(docs/collisions.md, "Speed on 2 ranks").
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
def _now(clock, timespec):
    """The monotonic clock (s), read by the C library's ``clock`` into ``timespec``."""
    clock(1, timespec.ctypes.data)            # CLOCK_MONOTONIC
    return timespec[0] + 1e-9 * timespec[1]


@njit(cache=True)
def _spin(clock, timespec, seconds, gap, edges):
    """Read the clock for ``seconds``; returns the gaps longer than ``gap`` (s) and their time per
    length class (``edges``, s: the classes below each edge, then above the last)."""
    lost = np.zeros(len(edges) + 1)
    count = 0
    start = last = _now(clock, timespec)
    while last - start < seconds:
        now = _now(clock, timespec)
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


def on_cores(target, cores, *args) -> list:
    """``target(core, *args, results)`` in one process per core, all at once; what each put in
    ``results``, sorted (by core: each result starts with it)."""
    results = Queue()
    workers = [Process(target=target, args=(core, *args, results)) for core in cores]
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


PIECE = 300_000      # array entries a piece of work reads, 10 times over (about 3 ms here)
FAST_SHARE = 0.1     # a core's best pace: the mean of its fastest tenth of the pieces
SLOW = 1.2           # a window counts as slow at this many times the core's best time or more


@njit(cache=True)
def _pieces(clock, timespec, seconds, values, order):
    """Repeat the piece of work for ``seconds``; returns the start and each piece's end (s,
    CLOCK_MONOTONIC: the same clock in every process)."""
    ends = np.empty(1_000_000)
    start = now = _now(clock, timespec)
    total, count = 0.0, 0
    while now - start < seconds and count < len(ends):
        for _ in range(10):
            for i in range(len(order)):
                total += values[order[i]] * 1.0000001
        now = _now(clock, timespec)
        ends[count] = now
        count += 1
    ends[0] += 0.0 * total   # (the sums used: the compiler cannot drop them)
    return start, ends[:count]


def pace_on(core: int, seconds: float, results: Queue) -> None:
    os.sched_setaffinity(0, {core})
    order = (np.arange(PIECE, dtype=np.int64) * 7919) % PIECE
    start, ends = _pieces(_clock_gettime, np.zeros(2, np.int64), seconds, np.linspace(0.0, 1.0, PIECE), order)
    results.put((core, start, ends))


def pace(label: str, cores, seconds: float, window: float) -> None:
    """The cores' pace and what cores in step lose (see the module's docstring)."""
    rows = on_cores(pace_on, cores, seconds)
    begin, end = max(start for _, start, _ in rows), min(ends[-1] for _, _, ends in rows)
    grid = np.arange(begin, end, window)
    done = []   # per core, the pieces done in each window (fractions at the edges)
    for core, start, ends in rows:
        times = np.concatenate([[start], ends])
        durations = np.diff(times)
        best = np.sort(durations)[:max(1, int(FAST_SHARE * len(durations)))].mean()
        work = np.diff(np.interp(grid, times, np.arange(len(times))))
        done.append(work)
        slow = np.mean(work < window / (SLOW * best))
        print(f"pace, {label}: core {core}: {len(ends)} pieces of {1e3 * best:.2f} ms at best; on average "
              f"{100 * (durations.mean() / best - 1):.1f} % slower than that; {100 * slow:.1f} % of its "
              f"{1e3 * window:g} ms windows {SLOW:g} x slower or more", flush=True)
    if len(rows) < 2:
        return
    done = np.array(done)
    slower, mean = done.min(axis=0).sum(), done.mean(axis=0).sum()
    print(f"pace, {label}: cores in step ({len(grid) - 1} windows of {1e3 * window:g} ms): the slower core's work "
          f"{100 * (1 - slower / mean):.1f} % below the cores' mean", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seconds", nargs="?", type=float, default=20.0)
    parser.add_argument("--cores", default="0,1")
    parser.add_argument("--gap-us", type=float, default=20.0)
    parser.add_argument("--window-ms", type=float, default=30.0)
    parser.add_argument("--pace-only", action="store_true", help="the pace with every core busy, not the gaps")
    args = parser.parse_args()
    cores = [int(c) for c in args.cores.split(",")]
    if not args.pace_only:
        _spin(_clock_gettime, np.zeros(2, np.int64), 0.01, 1.0, np.array(EDGES_US) * 1e-6)   # compiled once, here
        report("all busy", on_cores(spin_on, cores, args.seconds, args.gap_us), args.seconds, args.gap_us)
        report("alone", on_cores(spin_on, cores[:1], args.seconds, args.gap_us), args.seconds, args.gap_us)
    _pieces(_clock_gettime, np.zeros(2, np.int64), 0.01, np.zeros(2), np.zeros(2, np.int64))   # compiled once, here
    pace("all busy", cores, args.seconds, args.window_ms * 1e-3)
    if not args.pace_only:
        pace("alone", cores[:1], args.seconds, args.window_ms * 1e-3)


if __name__ == "__main__":
    sys.exit(main())
