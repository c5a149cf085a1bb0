"""Random packings of equal spheres in a box: a packed bed's particles, reproducible from a seed.

Collective rearrangement with growing spheres (after Jodrey & Tory 1985, *Phys. Rev. A* 32, 2347):
centres drawn uniformly in the box, then, while the spheres grow to their radius, every overlapping
pair is pushed apart along the line of centres, all pairs at once (numpy over the pair list of a
k-d tree). Each face of the box is either

- a wall: every sphere stays at least a radius from it. A wall orders the spheres next to it: the
  voidage within about a radius of it is higher (≈ 0.5 where the bulk has 0.38–0.40);
- a mirror (a symmetry plane of the flow): spheres may cross it, and keep clear of the mirror
  images of the others (not of their own), as the bed mirrored about that plane would be. The
  spheres near it are then packed nearly as in the bulk, so a column with symmetry sides has the
  voidage of a wide bed, without the ordered layers walls make.

No two spheres overlap (nor a sphere and another's image, nor a sphere and a wall) at ``radius``.
"""
from __future__ import annotations

import numpy as np

from .arrays import kd_tree


def random_packing(count: int, lower, upper, radius: float, mirrors=(False, False, False), seed: int = 1,
                   iterations: int = 50000) -> np.ndarray:
    """(count, 3) centres of ``count`` spheres of ``radius`` (m) in the box ``lower``–``upper`` (m).

    ``mirrors``: per axis, whether its two faces are mirrors (symmetry planes: spheres may cross
    them, centres stay inside the box) or walls (centres at least ``radius`` inside). Raises
    ValueError when the spheres jam before they reach their radius (the box is too full: random
    close packing is a solid fraction of ≈ 0.64 in the bulk)."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    mirrors = np.asarray(mirrors, bool)
    rng = np.random.default_rng(seed)
    target = radius * 1.01              # relaxed 1 % larger: the overlaps left (< 0.5 %) clear ``radius``
    inset = np.where(mirrors, 0.0, target)
    x = lower + inset + rng.random((count, 3)) * (upper - lower - 2 * inset)
    r = 0.5 * target
    for _ in range(iterations):
        shift, worst = separation(x, r, lower, upper, mirrors)
        x += shift
        x = np.clip(x, lower + np.where(mirrors, 0.0, r), upper - np.where(mirrors, 0.0, r))
        if r >= target and worst < 5e-3 * target:
            break
        if worst < 0.01 * r:            # grow slowly while the overlaps stay small: the spheres rearrange
            r = min(target, r * 1.003)
    else:
        raise ValueError(f"{count} spheres of radius {radius:g} m jam before they fit in the box {lower} – {upper}")
    return x


def separation(x: np.ndarray, r: float, lower: np.ndarray, upper: np.ndarray, mirrors: np.ndarray):
    """The displacement (n, 3) that pushes overlapping spheres of radius ``r`` apart (each half its
    overlap with each neighbour, under-relaxed), the mirror images of the others included; and the
    largest overlap (m)."""
    n = len(x)
    points, source = [x], [np.arange(n)]
    for axis in np.flatnonzero(mirrors):        # images of the spheres near a mirror, corners included
        images, sources = [], []
        for p, s in zip(points, source):
            for face in (lower[axis], upper[axis]):
                near = np.abs(p[:, axis] - face) < 2 * r
                image = p[near].copy()
                image[:, axis] = 2 * face - image[:, axis]
                images.append(image)
                sources.append(s[near])
        points, source = points + images, source + sources
    points, source = np.concatenate(points), np.concatenate(source)
    pairs = kd_tree(points).query_pairs(2 * r, output_type="ndarray")
    pairs = pairs[(pairs[:, 0] < n) & (source[pairs[:, 1]] != pairs[:, 0])]   # a real sphere, not its own image
    shift = np.zeros_like(x)
    if len(pairs) == 0:
        return shift, 0.0
    i, j = pairs[:, 0], pairs[:, 1]
    gap = points[j] - points[i]
    distance = np.maximum(np.linalg.norm(gap, axis=1), 1e-12 * r)
    overlap = 2 * r - distance
    push = (0.3 * overlap / distance)[:, None] * gap
    real = j < n                               # an image's own sphere moves by its own pair
    for axis in range(3):
        shift[:, axis] = (np.bincount(j[real], push[real, axis], minlength=n)
                          - np.bincount(i, push[:, axis], minlength=n))
    return shift, float(overlap.max())


def solid_fraction(x: np.ndarray, radius: float, lower, upper, spacing: float | None = None) -> float:
    """The share of the box ``lower``–``upper`` (m) that the spheres fill, counted on a lattice of
    points ``spacing`` apart (default: 1/40 of a diameter; the error is well under 1e-3)."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    spacing = radius / 20 if spacing is None else spacing
    counts = np.maximum(np.round((upper - lower) / spacing).astype(int), 1)
    axes = [lower[a] + (np.arange(counts[a]) + 0.5) * (upper[a] - lower[a]) / counts[a] for a in range(3)]
    tree = kd_tree(x)
    filled = 0
    for z in axes[2]:                           # a plane of points at a time: bounded memory
        gx, gy = np.meshgrid(axes[0], axes[1], indexing="ij")
        plane = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)])
        distance, _ = tree.query(plane, distance_upper_bound=radius)
        filled += int(np.count_nonzero(distance <= radius))
    return filled / int(np.prod(counts))
