"""Stopping on request: SIGTERM (a batch scheduler ahead of its wall-time limit) and SIGINT (Ctrl-C)
set a flag instead of ending the process; the time loop asks, collectively, after each step, so
every rank stops after the same step and the run writes its state before it leaves."""
from __future__ import annotations

import signal

import numpy as np
from mpi4py import MPI

SIGNALS = (signal.SIGTERM, signal.SIGINT)


class StopRequests:
    """``with StopRequests() as stops:`` — within the block the signals are caught; ``stops.agreed(comm)``
    (collective) is the signal number some rank received, or 0 (and whether a rank is past its
    wall-time limit)."""

    def __init__(self):
        self.received = 0
        self.stopping = 0
        self.previous = {}

    def __enter__(self) -> "StopRequests":
        for number in SIGNALS:
            self.previous[number] = signal.signal(number, self.catch)
        return self

    def __exit__(self, *exc):
        # After a stop, a signal sent to every rank may still be on its way to this one, which
        # had agreed on another rank's: caught, it is ignored; restored, it would kill this rank
        # while it writes the state (and mpirun the others), before the summary.
        if self.stopping:
            return
        for number, handler in self.previous.items():
            signal.signal(number, handler)

    def catch(self, number, frame):
        self.received = self.received or number

    def agreed(self, comm, past_limit: bool = False) -> tuple[int, bool]:
        """Collective. The first signal received on any rank (the largest number if several), or 0,
        and whether any rank found itself ``past_limit`` (its wall-time limit: each rank reads its
        own clock, so they must agree, or one would stop while the others wait for it in a step)."""
        flags = np.array([self.received, int(past_limit)], np.int64)
        if comm.size > 1:
            comm.Allreduce(MPI.IN_PLACE, flags, op=MPI.MAX)
        self.stopping = int(flags[0])
        return self.stopping, bool(flags[1])


def stop_message(state, signal_number: int, output) -> str:
    """What a run stopped by a signal says: the step, the time, where its checkpoint is."""
    return (f"stopped by {signal.Signals(signal_number).name} after step {state.step}, t = {state.time:.6g} s; "
            f"the state is in {output / 'checkpoint.h5'} (continue with --restart)")
