"""Small array helpers shared by the particle modules (no pmpm imports: anything may use them).

Rows of 3-vectors are (k, 3) arrays; these helpers avoid the overhead of np.cross and of a
Python loop over rows.
"""
from __future__ import annotations

import numpy as np


def summed(index: np.ndarray, weights: np.ndarray, n: int) -> np.ndarray:
    """(n,) float sums of ``weights`` by ``index``: np.bincount, whose sums come out as integers
    when ``index`` is empty (numpy 1.24), which an MPI buffer or an HDF5 dataset of floats on
    another rank then misreads."""
    return np.bincount(index, weights, minlength=n).astype(float, copy=False)


def sum_rows(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) float sums of the (k, 3) ``values`` by row ``index`` (``summed`` per component)."""
    return np.column_stack([summed(index, values[:, d], n) for d in range(3)])


def members(values: np.ndarray, ascending: np.ndarray) -> np.ndarray:
    """(len(values),) bool: which of ``values`` are in ``ascending`` (sorted): np.isin by binary
    search, without np.isin's sort of both (a few times faster on the arrays of a contact step)."""
    at = np.searchsorted(ascending, values)
    found = at < len(ascending)
    found[found] = ascending[at[found]] == values[found]
    return found


def cross(a, b) -> np.ndarray:
    """a × b for 3-vectors or (k, 3) rows, broadcast (np.cross is slow on small arrays)."""
    a, b = np.asarray(a), np.asarray(b)
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), np.result_type(a, b))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def rotation_matrix(angle_vectors) -> np.ndarray:
    """Rotation matrices by the rotation vectors θ (Rodrigues): by |θ| radians about θ/|θ|.

    Parameters
    ----------
    angle_vectors : (3,) or (k, 3) rotation vectors (rad); a zero one gives the identity.

    Returns
    -------
    (3, 3) or (k, 3, 3): I + sin|θ| [u]× + (1 − cos|θ|) [u]×², u = θ/|θ|.
    """
    theta = np.asarray(angle_vectors, float)
    angle = np.sqrt(np.sum(theta * theta, axis=-1))[..., None, None]
    unit = np.divide(theta, angle[..., 0], out=np.zeros_like(theta), where=angle[..., 0] > 0)
    k = np.zeros(theta.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -unit[..., 2], unit[..., 1], -unit[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = unit[..., 2], -unit[..., 1], unit[..., 0]
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def rotate(vectors, angle_vectors) -> np.ndarray:
    """3-vectors rotated by the rotation vectors θ (``rotation_matrix``), row by row.

    vectors : (3,) or (k, 3); angle_vectors : (3,) or (k, 3), broadcast against ``vectors``.
    """
    return np.einsum("...ij,...j->...i", rotation_matrix(angle_vectors), np.asarray(vectors, float))


# scipy.spatial and scipy.sparse are loaded on first use: a run without a flow that never places,
# checks or attracts particles by distance does without them (part of every start's imports).
def kd_tree(points: np.ndarray):
    """scipy's cKDTree of ``points`` (k, 3)."""
    from scipy.spatial import cKDTree
    return cKDTree(points)


def csr_matrix(values: np.ndarray, rows: np.ndarray, columns: np.ndarray, shape: tuple):
    """scipy's CSR matrix of ``shape`` with ``values`` at (``rows``, ``columns``) (duplicates summed
    when converted)."""
    from scipy.sparse import csr_matrix as csr
    return csr((values, (rows, columns)), shape=shape)
