"""Small array helpers shared by the particle modules (no pmpm imports: anything may use them).

Rows of 3-vectors are (k, 3) arrays; these helpers avoid the overhead of np.cross and of a
Python loop over rows.
"""
from __future__ import annotations

import numpy as np


def sum_rows(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) sums of the (k, 3) ``values`` by row ``index`` (np.bincount per component)."""
    return np.column_stack([np.bincount(index, values[:, d], minlength=n) for d in range(3)])


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


def rotate(vectors, angle_vectors) -> np.ndarray:
    """Rotate 3-vectors by the rotation vectors θ (Rodrigues): by |θ| radians about θ/|θ|.

    Parameters
    ----------
    vectors : (3,) or (k, 3)
    angle_vectors : (3,) or (k, 3) rotation vectors (rad), broadcast against ``vectors``;
        a zero row leaves its vector as it is.

    Returns
    -------
    (k, 3) or (3,) the rotated vectors, v cos|θ| + (u × v) sin|θ| + u (u·v)(1 − cos|θ|), u = θ/|θ|.
    """
    v, theta = np.asarray(vectors, float), np.asarray(angle_vectors, float)
    angle = np.sqrt(np.sum(theta * theta, axis=-1, keepdims=True))
    unit = np.divide(theta, angle, out=np.zeros_like(theta), where=angle > 0)
    cos, sin = np.cos(angle), np.sin(angle)
    return v * cos + cross(unit, v) * sin + unit * np.sum(unit * v, axis=-1, keepdims=True) * (1.0 - cos)
