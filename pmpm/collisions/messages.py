"""MPI's messages called from compiled kernels: the block sweeps (``block``) pass shadow copies
between ranks after every sweep, 10,000 times a hopper discharge, and the Python around each call
through mpi4py cost more than the message (docs/collisions_log.md, "Sixteenth session").

A kernel calls the MPI library's C functions by name (numba's ``ExternalFunction``: cached like any
kernel, the symbol resolved when the kernel is loaded, in the library mpi4py has loaded). The
handles (communicator, datatype, operation) go in as integers from mpi4py (``handles``); requests
and statuses live in byte buffers of the library's own sizes (``requests``, ``statuses``). So the
calls hold for any MPI whose handles are pointers or integers passed in a 64-bit register (Open MPI's
pointers, MPICH's ints on x86-64 and arm64).
"""
from __future__ import annotations

import ctypes
from functools import cache
from typing import NamedTuple

import numpy as np
from numba import njit, types

_ADDRESS, _INT = types.intp, types.int32
_isend = types.ExternalFunction("MPI_Isend", _INT(_ADDRESS, _INT, _ADDRESS, _INT, _INT, _ADDRESS, _ADDRESS))
_recv = types.ExternalFunction("MPI_Recv", _INT(_ADDRESS, _INT, _ADDRESS, _INT, _INT, _ADDRESS, _ADDRESS))
_waitall = types.ExternalFunction("MPI_Waitall", _INT(_INT, _ADDRESS, _ADDRESS))
_wait = types.ExternalFunction("MPI_Wait", _INT(_ADDRESS, _ADDRESS))
_iallreduce = types.ExternalFunction("MPI_Iallreduce",
                                     _INT(_ADDRESS, _ADDRESS, _INT, _ADDRESS, _ADDRESS, _ADDRESS, _ADDRESS))
clock = types.ExternalFunction("MPI_Wtime", types.float64())   # seconds


class Handles(NamedTuple):
    """What a kernel needs to send on ``comm``: its handle, float64's and MAX's, and the sizes of a
    request and a status (bytes)."""

    comm: int
    double: int
    maximum: int
    request_size: int
    status_size: int


def handles(comm) -> Handles:
    """The handles of mpi4py's ``comm`` for the kernels (the MPI library's symbols made visible to
    them first)."""
    from mpi4py import MPI
    _expose_library()
    return Handles(MPI._handleof(comm), MPI._handleof(MPI.DOUBLE), MPI._handleof(MPI.MAX),
                   MPI._sizeof(MPI.Request), MPI._sizeof(MPI.Status))


@cache
def _expose_library() -> None:
    """Make the MPI library's symbols resolvable by the compiled kernels (mpi4py loads Open MPI's
    globally already; any other is loaded again, globally, from where the process mapped it)."""
    if hasattr(ctypes.CDLL(None), "MPI_Isend"):
        return
    from llvmlite import binding
    with open("/proc/self/maps") as maps:
        paths = {line.split()[-1] for line in maps if "/libmpi" in line and ".so" in line}
    for path in sorted(paths):
        binding.load_library_permanently(path)


@njit(cache=True)
def requests(count, mpi):
    """Room for ``count`` requests (a byte buffer: ``request(buffer, k, mpi)`` is the k-th's address)."""
    return np.zeros(max(count, 1) * mpi[3], np.uint8)


@njit(cache=True)
def statuses(count, mpi):
    """Room for ``count`` statuses (bytes)."""
    return np.zeros(max(count, 1) * mpi[4], np.uint8)


@njit(cache=True)
def request(buffer, k, mpi):
    return buffer.ctypes.data + k * mpi[3]


@njit(cache=True)
def checked(code):
    if code != 0:
        raise RuntimeError("an MPI call failed in a compiled kernel")


@njit(cache=True)
def post(rows, to, tag, held, k, mpi):
    """Send the C-contiguous float64 ``rows`` (2-D) to rank ``to`` without waiting; ``held[k]``'s
    request (``requests``) is done once the send buffer may change."""
    checked(_isend(rows.ctypes.data, rows.size, mpi[1], to, tag, mpi[0], request(held, k, mpi)))


@njit(cache=True)
def receive(rows, source, tag, status, mpi):
    """Receive into the C-contiguous float64 ``rows`` (2-D) from rank ``source``, waiting."""
    checked(_recv(rows.ctypes.data, rows.size, mpi[1], source, tag, mpi[0], status.ctypes.data))


@njit(cache=True)
def wait_all(held, count, status, mpi):
    """Wait for the first ``count`` requests of ``held``."""
    if count > 0:
        checked(_waitall(count, held.ctypes.data, status.ctypes.data))


@njit(cache=True)
def wait(held, k, status, mpi):
    checked(_wait(request(held, k, mpi), status.ctypes.data))


@njit(cache=True)
def post_maximum(value, into, held, k, mpi):
    """Start the largest of ``value[0]`` over the ranks into ``into[0]`` (a one-element slice of
    each), done once ``held[k]``'s request is."""
    checked(_iallreduce(value.ctypes.data, into.ctypes.data, 1, mpi[1], mpi[2], mpi[0], request(held, k, mpi)))
