"""Which rank owns which cells: recursive coordinate bisection of the cell centres, on rank 0.

A partition that depends on the case alone makes a run repeatable: PT-Scotch, DMPlex's default
partitioner here, partitions differently from one run to the next, so the ranks summed their
cells in other orders and two identical 2-rank runs differed by round-off. Bisection by
coordinates gives each rank a compact block of space (a slab, then boxes), which is also what
particle ownership wants; its cut is a plane, a little longer than a graph partitioner's on
irregular domains.

Where particles sit in a flow, each cut also splits their coupling work: a bed that fills the
lower half of a tall column, cut across its height, would leave one rank all of it. Every cut
halves the cells; of the planes that do, it takes the one across the longest extent whose sides
share the particles' work in proportion (within ``WORK_TOLERANCE``), else the fairest.
"""
from __future__ import annotations

import numpy as np
from petsc4py import PETSc

# how far from its due share of the particles' work a side may be before a cut across a
# shorter extent is preferred (a longer cut costs the flow a little more exchange)
WORK_TOLERANCE = 0.1


def coordinate_bisection(centres: np.ndarray, parts: int, work_at: np.ndarray | None = None,
                         work: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(n,) the part of each point of ``centres`` (n, 3): split the points in two by a plane, in
    proportion to the parts on each side, and again, until one part is left. The plane is across
    the points' longest extent unless ``work`` (m,) at the points ``work_at`` (m, 3), e.g. the
    particles' volumes at their centres, would then be shared unfairly (module docstring). Ties in
    a coordinate go by the points' order, so the result depends on the points alone.

    Also each part's box (2, parts, 3), [lower, upper) with the outer sides at ±inf: the planes lie
    halfway between the last point of one side and the first of the other (on a box mesh, where the
    cells between them meet), so a point's box is its part wherever the points are not tied."""
    if work_at is None:
        work_at, work = np.zeros((0, 3)), np.zeros(0)
    part = np.empty(len(centres), np.int64)
    boxes = np.empty((2, parts, 3))
    pending = [(np.arange(len(centres)), np.arange(len(work_at)), 0, parts, np.full(3, -np.inf), np.full(3, np.inf))]
    while pending:
        points, loads, first, count, lower, upper = pending.pop()
        if count == 1:
            part[points] = first
            boxes[0, first], boxes[1, first] = lower, upper
            continue
        left = count // 2
        cut = int(round(len(points) * left / count))
        along = centres[points]
        extents = along.max(axis=0, initial=-np.inf) - along.min(axis=0, initial=np.inf)
        best, share, total = None, work[loads], work[loads].sum()
        for axis in np.argsort(-extents, kind="stable"):
            order = points[np.lexsort((points, along[:, axis]))]
            plane = centres[order[cut], axis] if cut < len(order) else np.inf
            on_left = work_at[loads, axis] < plane
            unfair = abs(share[on_left].sum() / total - left / count) if total > 0 else 0.0
            if best is None or unfair < best[0]:
                best = (unfair, order, on_left, axis, plane)
            if unfair <= WORK_TOLERANCE:
                break
        _, order, on_left, axis, plane = best
        if 0 < cut < len(order):   # halfway to the last point on the lower side
            plane = 0.5 * (plane + centres[order[cut - 1], axis])
        upper_left, lower_right = upper.copy(), lower.copy()
        upper_left[axis] = lower_right[axis] = plane
        pending += [(order[:cut], loads[on_left], first, left, lower, upper_left),
                    (order[cut:], loads[~on_left], first + left, count - left, lower_right, upper)]
    return part, boxes


def set_coordinate_partition(dm, comm, centres: np.ndarray | None, work_at: np.ndarray | None = None,
                             work: np.ndarray | None = None) -> np.ndarray:
    """Collective. Make ``dm``'s next ``distribute`` give rank r the cells whose part is r, the
    parts from ``coordinate_bisection`` of the cell centres (n_cells, 3) and the ``work`` at
    ``work_at``, which rank 0 passes (it holds the whole undistributed mesh) and the others pass
    as None. Returns the parts' boxes (2, ranks, 3) on every rank."""
    partitioner = dm.getPartitioner()
    partitioner.setType(PETSc.Partitioner.Type.SHELL)
    boxes = None
    if comm.rank == 0:
        part, boxes = coordinate_bisection(centres, comm.size, work_at, work)
        sizes = np.bincount(part, minlength=comm.size)
        points = np.argsort(part, kind="stable")
    else:
        sizes, points = np.zeros(comm.size, np.int64), np.zeros(0, np.int64)
    partitioner.setShellPartition(comm.size, sizes.astype(PETSc.IntType), points.astype(PETSc.IntType))
    return comm.bcast(boxes, root=0)
