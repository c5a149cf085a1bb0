"""Which rank owns which cells: recursive coordinate bisection of the cell centres, on rank 0.

A partition that depends on the mesh alone makes a run repeatable: PT-Scotch, DMPlex's default
partitioner here, partitions differently from one run to the next, so the ranks summed their
cells in other orders and two identical 2-rank runs differed by round-off. Bisection by
coordinates gives each rank a compact block of space (a slab, then boxes), which is also what
particle ownership wants; its cut is a plane, a little longer than a graph partitioner's on
irregular domains.
"""
from __future__ import annotations

import numpy as np
from petsc4py import PETSc


def coordinate_bisection(centres: np.ndarray, parts: int) -> np.ndarray:
    """(n,) the part of each point (n, 3): split the points in two across their longest extent, in
    proportion to the parts on each side, and again, until one part is left. Ties in a coordinate
    go by the points' order, so the result depends on the points alone."""
    part = np.empty(len(centres), np.int64)
    pending = [(np.arange(len(centres)), 0, parts)]
    while pending:
        points, first, count = pending.pop()
        if count == 1:
            part[points] = first
            continue
        left = count // 2
        along = centres[points]
        axis = int(np.argmax(along.max(axis=0, initial=-np.inf) - along.min(axis=0, initial=np.inf)))
        order = points[np.lexsort((points, along[:, axis]))]
        cut = int(round(len(points) * left / count))
        pending += [(order[:cut], first, left), (order[cut:], first + left, count - left)]
    return part


def set_coordinate_partition(dm, comm, centres: np.ndarray | None) -> None:
    """Collective. Make ``dm``'s next ``distribute`` give rank r the cells whose part is r, the
    parts from ``coordinate_bisection`` of the cell centres (n_cells, 3), which rank 0 passes (it
    holds the whole undistributed mesh) and the others pass as None."""
    partitioner = dm.getPartitioner()
    partitioner.setType(PETSc.Partitioner.Type.SHELL)
    if comm.rank == 0:
        part = coordinate_bisection(centres, comm.size)
        sizes = np.bincount(part, minlength=comm.size)
        points = np.argsort(part, kind="stable")
    else:
        sizes, points = np.zeros(comm.size, np.int64), np.zeros(0, np.int64)
    partitioner.setShellPartition(comm.size, sizes.astype(PETSc.IntType), points.astype(PETSc.IntType))
