"""Per-particle sums over the (particle, cell) pairs of all ranks, in one Allreduce."""
from __future__ import annotations

import numpy as np
from mpi4py import MPI


def particle_sums(comm, n: int, particle: np.ndarray, r: np.ndarray, mass: np.ndarray, *momenta: np.ndarray):
    """Collective. Per particle, summed over all ranks in one Allreduce of (n, 2 + 6 k) doubles.

    Parameters
    ----------
    n : number of particles
    particle : (m,) the particle of each pair on this rank
    r : (m, 3) from the particle's centre to the cell centre (m)
    mass : (m,) a mass per pair (kg)
    momenta : k arrays (m, 3), a momentum per pair (kg m/s)

    Returns
    -------
    mass (n,), its moment of inertia about the centre (n,) (isotropic share, 2/3 |r|²), and for each
    momentum its sum and its moment r × it, (n, 6).
    """
    sums = np.zeros((n, 2 + 6 * len(momenta)))
    sums[:, 0] = np.bincount(particle, mass, minlength=n)
    sums[:, 1] = np.bincount(particle, mass * (2.0 / 3.0) * np.einsum("ij,ij->i", r, r), minlength=n)
    for i, momentum in enumerate(momenta):
        spin = np.cross(r, momentum)
        for d in range(3):
            sums[:, 2 + 6 * i + d] = np.bincount(particle, momentum[:, d], minlength=n)
            sums[:, 5 + 6 * i + d] = np.bincount(particle, spin[:, d], minlength=n)
    if comm.size > 1:
        comm.Allreduce(MPI.IN_PLACE, sums, op=MPI.SUM)
    return sums[:, 0], sums[:, 1], [sums[:, 2 + 6 * i: 8 + 6 * i] for i in range(len(momenta))]
