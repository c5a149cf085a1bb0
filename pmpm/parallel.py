"""Small MPI helpers: root-only printing, agreeing on errors, offsets, reductions.

Every function here that takes a communicator is collective unless it says otherwise.
"""
from __future__ import annotations

import sys

import numpy as np
from mpi4py import MPI

from .errors import CaseError, NumericalError, one_line


def print0(comm, *args, **kwargs):
    """Print on rank 0 only (not collective)."""
    if comm.rank == 0:
        print(*args, **kwargs, flush=True)


def warn(comm, message: str):
    """A warning on stderr, tagged with the rank when there are several (not collective)."""
    tag = f"[rank {comm.rank}] " if comm.size > 1 else ""
    print(f"pmpm: warning: {tag}{one_line(message)}", file=sys.stderr, flush=True)


def agree(comm, error: Exception | None):
    """Collective. Raise on every rank if any rank met an error, with the lowest such rank's message.

    Checks that can fail on one rank only (a file, a particle outside a rank's cells) call this
    so that all ranks leave together and no rank waits in a later collective.
    """
    if comm.size == 1:
        if error is not None:
            raise error
        return
    mine = None if error is None else (getattr(error, "exit_status", 1), str(error))
    reports = [r for r in comm.allgather(mine) if r is not None]
    if not reports:
        return
    status, message = reports[0]
    raise {2: CaseError, 3: NumericalError}.get(status, RuntimeError)(message)


def exscan_offset(comm, count: int) -> int:
    """Collective. Sum of ``count`` over lower ranks (the offset of this rank's block)."""
    offset = comm.exscan(int(count))
    return 0 if comm.rank == 0 or offset is None else int(offset)


def allreduce_sum(comm, array: np.ndarray) -> np.ndarray:
    """Collective. Element-wise sum of a float or int array over ranks (a new array)."""
    array = np.ascontiguousarray(array)
    if comm.size == 1:
        return array.copy()
    out = np.empty_like(array)
    comm.Allreduce(array, out, op=MPI.SUM)
    return out


def allreduce_max(comm, value: float) -> float:
    """Collective. Maximum of a scalar over ranks."""
    return comm.allreduce(value, op=MPI.MAX) if comm.size > 1 else value


def allgather_rows(comm, rows: np.ndarray) -> np.ndarray:
    """Collective. Concatenate each rank's rows (n_i, ...) in rank order on every rank."""
    rows = np.ascontiguousarray(rows)
    if comm.size == 1:
        return rows.copy()
    counts = np.array(comm.allgather(rows.shape[0]))
    row_size = int(np.prod(rows.shape[1:], dtype=int))
    out = np.empty((counts.sum(),) + rows.shape[1:], dtype=rows.dtype)
    mpi_type = MPI._typedict[rows.dtype.char]
    comm.Allgatherv(rows, [out, counts * row_size, None, mpi_type])
    return out
