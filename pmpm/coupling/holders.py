"""Where a coupled step's per-particle sums meet.

Each rank sums over the (particle, cell) pairs of its owned cells only, so a particle's drag, the
fluid under it, its cells' response and the like are sums over every rank whose cells it touches.
On one rank, or where every rank holds every particle, those sums meet in an Allreduce over all
particles. Where ranks own particles (``pmpm.ownership``), a rank holds its own and ghost copies of
those that reach into its cells (``Halo``, built for the step by ``pmpm.flow_stage.held_for_the_flow``):
the sums then meet among the particle's holders only — the ghosts' partial sums go to the owner,
and the owner's total back to the ghosts — so every holder applies the same update to its copy,
and no array over every particle of the run exists on any rank.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mpi4py import MPI

from ..halo import Halo


@dataclass(frozen=True)
class Holders:
    """The ranks that hold each particle of this step (see the module docstring).

    comm : the communicator of the run
    halo : the step's ghost copies, or None where every rank holds every particle
    owned : (n,) bool, the local rows this rank owns (all where ``halo`` is None)
    """

    comm: object
    halo: Halo | None
    owned: np.ndarray

    @classmethod
    def everywhere(cls, comm, n: int) -> "Holders":
        """Every rank holds all ``n`` particles."""
        return cls(comm, None, np.ones(n, bool))

    def sum(self, array: np.ndarray) -> np.ndarray:
        """Collective. ``array`` (a row per local particle, C-contiguous), each row summed over the
        particle's holders, in place; returned."""
        return self._over_holders(array, MPI.SUM)

    def max(self, array: np.ndarray) -> np.ndarray:
        """Collective. As ``sum``, the largest over the holders."""
        return self._over_holders(array, MPI.MAX)

    def _over_holders(self, array: np.ndarray, op) -> np.ndarray:
        if self.halo is not None:
            return self.halo.sum_over_holders(array) if op is MPI.SUM else self.halo.max_over_holders(array)
        if self.comm.size > 1:
            self.comm.Allreduce(MPI.IN_PLACE, array, op=op)
        return array

    def from_owners(self, array: np.ndarray) -> np.ndarray:
        """Collective. ``array`` with each ghost row its owner's, in place (a value only the owner
        knows for certain, e.g. remembered from the last step); returned."""
        if self.halo is not None:
            self.halo.to_ghosts(array)
        return array

    def across_ranks(self, array: np.ndarray) -> np.ndarray:
        """Collective. Sums that each rank took over its owned rows (``owned``), summed over the
        ranks in place; where every rank holds every particle they are whole already."""
        if self.halo is not None and self.comm.size > 1:
            self.comm.Allreduce(MPI.IN_PLACE, array, op=MPI.SUM)
        return array

    def largest(self, value: int) -> int:
        """Collective. The largest of ``value`` over the ranks where ranks hold different particles."""
        return self.comm.allreduce(value, op=MPI.MAX) if self.halo is not None else value
