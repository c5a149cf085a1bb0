"""Where a run on several ranks waits: every blocking MPI call of the time loop clocked on each rank.

    mpirun -n 2 .venv/bin/python bench/rank_waits.py CASE [pmpm options, e.g. --output DIR --restart FILE]

Runs pmpm's command (``pmpm.__main__.main``) with its communicator replaced by one that times
each blocking call it makes (the collectives and the waits on nonblocking messages; the mesh
keeps the plain world communicator, which PETSc needs), adds the waits the block sweeps clock
themselves (their messages are sent from compiled code, ``pmpm.collisions.block``: column
``sweeps``), then prints per rank the whole run's wall
time, the seconds spent in each kind of call and the rest, its busy time. A rank that waits much
longer than another is waiting for it: the difference of their busy times is the imbalance,
measured without a profiler (which slows the ranks unevenly) and without the noise of wall times
that vary by tens of per cent from one minute to the next on a shared machine (docs/collisions_log.md,
"Eighth session"). Last, the sweeps step by step: how far the busiest rank's sweeps (waits aside)
lie above the ranks' mean, summed over the dense steps (the time the ranks in step lose there), and
how much of it the ranks' contact counts explain; the rest is the pace of their cores
(``bench/cpu_gaps.py``).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

BLOCKING = ("allgather", "allreduce", "alltoall", "gather", "bcast", "Allreduce", "Allgather", "Alltoall",
            "Alltoallv", "Barrier", "Recv")
clock: dict[str, list] = {}


def clocked(name, call):
    def timed(*args, **kwargs):
        start = time.perf_counter()
        try:
            return call(*args, **kwargs)
        finally:
            entry = clock.setdefault(name, [0, 0.0])
            entry[0] += 1
            entry[1] += time.perf_counter() - start
    return timed


class ClockedComm(MPI.Intracomm):
    """COMM_WORLD, its blocking calls clocked."""


class ClockedRequest(MPI.Request):
    """``MPI.Request`` with ``Waitall`` clocked (pmpm waits on its messages with it)."""


for method in BLOCKING:
    setattr(ClockedComm, method, clocked(method, getattr(MPI.Intracomm, method)))
ClockedRequest.Waitall = staticmethod(clocked("Waitall", MPI.Request.Waitall))


def clocked_sweeps(sweeps):
    """The block sweeps' kernel, the seconds it waited for other ranks added to the clock; each
    call's seconds, waits and contacts kept in ``sweep_calls``."""
    def timed(*args):
        start = time.perf_counter()
        done, waited = sweeps(*args)
        entry = clock.setdefault("sweeps", [0, 0.0])
        entry[0] += 1
        entry[1] += waited
        sweep_calls.append((time.perf_counter() - start, waited, len(args[0][0]) + len(args[1][0])))
        return done, waited
    return timed


sweep_calls: list = []   # per call (a dense step): seconds, seconds waited, contacts (border and inner)


def sweeps_in_step(calls: list) -> str:
    """What the ranks' sweeps lose to each other, step by step: each dense step's sweeps last as
    long as the busiest rank's (waits aside), so the sum over steps of the busiest rank's busy
    time less the ranks' mean is lost. The part of it the contacts explain (each rank's contacts at
    the run's mean time per contact) is the imbalance of the work; the rest is the ranks' pace."""
    busy = np.array([[seconds - waited for seconds, waited, _ in rank] for rank in calls]).T    # (steps, ranks)
    contacts = np.array([[count for _, _, count in rank] for rank in calls], float).T
    per_contact = busy.sum() / max(contacts.sum(), 1.0)
    lost = (busy.max(axis=1) - busy.mean(axis=1)).sum()
    explained = per_contact * (contacts.max(axis=1) - contacts.mean(axis=1)).sum()
    return (f"the sweeps, step by step: the busiest rank {lost:.2f} s above the ranks' mean over {len(busy)} "
            f"steps ({100 * lost / busy.mean(axis=1).sum():.1f} %); the contacts' imbalance explains "
            f"{explained:.2f} s of it, the ranks' pace the rest")


def main() -> None:
    world = MPI.COMM_WORLD
    MPI.COMM_WORLD, MPI.Request = ClockedComm(world), ClockedRequest
    from pmpm.collisions import jit
    block = jit.kernels().block
    block.sweeps = clocked_sweeps(block.sweeps)
    import pmpm.simulation as simulation
    build_mesh = simulation.build_mesh
    simulation.build_mesh = lambda comm, case: build_mesh(world, case)
    from pmpm.__main__ import main as pmpm
    sys.argv = ["pmpm"] + sys.argv[1:]
    start = time.perf_counter()
    status = pmpm(sys.argv[1:])   # (not ``python -m pmpm``'s way, which ends the process at once)
    if status:
        raise SystemExit(status)
    wall = time.perf_counter() - start
    ranks = world.gather((wall, dict(clock)), root=0)
    sweeps = world.gather(sweep_calls, root=0)
    if world.rank != 0:
        return
    names = sorted({name for _, calls in ranks for name in calls})
    print(f"{'rank':>4} {'wall s':>8} {'waits s':>8} {'busy s':>8}  " + " ".join(f"{n:>10}" for n in names))
    for rank, (wall, calls) in enumerate(ranks):
        waits = sum(seconds for _, seconds in calls.values())
        print(f"{rank:>4} {wall:8.2f} {waits:8.2f} {wall - waits:8.2f}  "
              + " ".join(f"{calls.get(n, (0, 0.0))[1]:10.2f}" for n in names))
    busy = [wall - sum(seconds for _, seconds in calls.values()) for wall, calls in ranks]
    print(f"busiest rank {max(range(len(busy)), key=busy.__getitem__)}: {max(busy) - min(busy):.2f} s busier "
          f"than the least busy; calls per rank: " + ", ".join(f"{n} {ranks[0][1].get(n, (0,))[0]}" for n in names))
    if len({len(rank) for rank in sweeps}) == 1 and sweeps[0]:
        print(sweeps_in_step(sweeps))


if __name__ == "__main__":
    main()
