"""Sums over the (particle, cell) pairs, compiled (numba): per particle over the ranks that hold
it (``fluid_sums``, ``largest_slip``; ``holders.Holders``), or per owned cell (``cell_targets``). Each is one pass
over the pairs, the rigid motion U = v + ω × r of a pair computed in place: the numpy version's
gathers, cross products and bincounts over (pairs, 3) temporaries were most of the penalty's time
in a dense bed (docs/coupling.md)."""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _slip(u, c, v, omega, p, rx, ry, rz):
    """u − U at the pair's cell, U = v + ω × r the particle's rigid motion there."""
    return (u[c, 0] - v[p, 0] - (omega[p, 1] * rz - omega[p, 2] * ry),
            u[c, 1] - v[p, 1] - (omega[p, 2] * rx - omega[p, 0] * rz),
            u[c, 2] - v[p, 2] - (omega[p, 0] * ry - omega[p, 1] * rx))


@njit(cache=True)
def _fluid_sums(n, particle, cell, offset, u, mass, weight, v, omega):
    out = np.zeros((n, 14))
    with_slip = len(weight) > 0
    for k in range(len(particle)):
        p, c = particle[k], cell[k]
        rx, ry, rz = offset[k, 0], offset[k, 1], offset[k, 2]
        ux, uy, uz = u[c, 0], u[c, 1], u[c, 2]
        m = mass[k]
        out[p, 0] += m
        out[p, 1] += m * (2.0 / 3.0) * (rx * rx + ry * ry + rz * rz)
        mx, my, mz = m * ux, m * uy, m * uz
        out[p, 2] += mx
        out[p, 3] += my
        out[p, 4] += mz
        out[p, 5] += ry * mz - rz * my
        out[p, 6] += rz * mx - rx * mz
        out[p, 7] += rx * my - ry * mx
        if with_slip:
            w = weight[k]
            sx, sy, sz = _slip(u, c, v, omega, p, rx, ry, rz)
            sx, sy, sz = w * sx, w * sy, w * sz
            out[p, 8] += sx
            out[p, 9] += sy
            out[p, 10] += sz
            out[p, 11] += ry * sz - rz * sy
            out[p, 12] += rz * sx - rx * sz
            out[p, 13] += rx * sy - ry * sx
    return out


def fluid_sums(holders, n: int, particle: np.ndarray, cell: np.ndarray, offset: np.ndarray, u: np.ndarray,
               mass: np.ndarray, weight: np.ndarray | None = None, v: np.ndarray | None = None,
               omega: np.ndarray | None = None):
    """Collective. Per particle, summed over its pairs on the ranks that hold it in one exchange.

    Parameters
    ----------
    holders : ``holders.Holders``, how the sums meet
    n : number of particles
    particle, cell : (m,) each pair's particle and owned cell
    offset : (m, 3) r, from the particle's centre to the cell centre (m)
    u : (n_cells, 3) the fluid velocity per cell (m/s)
    mass : (m,) a mass per pair (kg)
    weight : (m,) a weight per pair (kg) for the slip sums, with the particles' motion ``v``,
        ``omega`` (n, 3); None: no slip sums

    Returns
    -------
    Σ mass (n,); its moment of inertia about the centre (n,), the isotropic share ⅔ |r|²;
    Σ mass u and its moment Σ r × mass u (n, 6); and (None without ``weight``) Σ weight (u − U)
    and its moment (n, 6), U = v + ω × r the particle's rigid motion at the cell centre.
    """
    with_slip = weight is not None
    if not with_slip:
        weight, v, omega = np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
    sums = holders.sum(_fluid_sums(n, particle, cell, offset, u, mass, weight, v, omega))
    return sums[:, 0], sums[:, 1], sums[:, 2:8], (sums[:, 8:14] if with_slip else None)


@njit(cache=True)
def _largest_slip(n, particle, cell, offset, u, v, omega):
    speed = np.zeros(n)
    for k in range(len(particle)):
        p, c = particle[k], cell[k]
        sx, sy, sz = _slip(u, c, v, omega, p, offset[k, 0], offset[k, 1], offset[k, 2])
        speed[p] = max(speed[p], np.sqrt(sx * sx + sy * sy + sz * sz))
    return speed


def largest_slip(holders, n: int, particle, cell, offset, u, v, omega) -> np.ndarray:
    """Collective. (n,) the largest |u − U| over each particle's pairs on the ranks that hold it
    (arguments as ``fluid_sums``)."""
    return holders.max(_largest_slip(n, particle, cell, offset, u, v, omega))


@njit(cache=True)
def cell_targets(n_owned, particle, cell, offset, weight, v, omega):
    """Local. Per owned cell, Σ weight (n_owned,) and Σ weight U (n_owned, 3) over its pairs, U =
    v + ω × r the rigid motion of the pair's particle at the cell centre (arguments as ``fluid_sums``)."""
    diagonal = np.zeros(n_owned)
    target = np.zeros((n_owned, 3))
    for k in range(len(particle)):
        p, c = particle[k], cell[k]
        rx, ry, rz = offset[k, 0], offset[k, 1], offset[k, 2]
        w = weight[k]
        diagonal[c] += w
        target[c, 0] += w * (v[p, 0] + omega[p, 1] * rz - omega[p, 2] * ry)
        target[c, 1] += w * (v[p, 1] + omega[p, 2] * rx - omega[p, 0] * rz)
        target[c, 2] += w * (v[p, 2] + omega[p, 0] * ry - omega[p, 1] * rx)
    return diagonal, target
