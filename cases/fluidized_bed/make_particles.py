"""The fluidized bed's glass beads: ``count`` spheres (d = 3 mm, 2500 kg/m³) packed at random
(``pmpm.packing.random_packing``, clear of the column's walls) at a solid fraction of 0.5 above the
inlet. Writes particles.txt beside this script (10,000 beads: about a minute).

    .venv/bin/python cases/fluidized_bed/make_particles.py [count [width depth]]

``width``, ``depth``: the column's cross-section (m), default 0.09 × 0.03 (the case's mesh).
"""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from pmpm.packing import random_packing  # noqa: E402

DIAMETER, DENSITY = 0.003, 2500.0
FILL = 0.5                              # solid fraction of the initial packing (random close packing: 0.64)


def beads(count: int, width: float, depth: float, seed: int = 1) -> np.ndarray:
    """(count, 5) rows x y z radius density: the beads packed at ``FILL`` on the floor z = 0 of a
    column ``width`` × ``depth`` (m)."""
    height = count * np.pi / 6 * DIAMETER ** 3 / (FILL * width * depth)
    x = random_packing(count, [0.0, 0.0, 0.0], [width, depth, height], DIAMETER / 2, seed=seed)
    return np.column_stack([x, np.full(count, DIAMETER / 2), np.full(count, DENSITY)])


def write(path: Path, table: np.ndarray) -> None:
    np.savetxt(path, table, header="x y z radius density", comments="", fmt="%.9g")


def main():
    count = int(sys.argv[1]) if len(sys.argv) > 1 else 10000
    width, depth = (float(sys.argv[2]), float(sys.argv[3])) if len(sys.argv) > 3 else (0.09, 0.03)
    path = Path(__file__).with_name("particles.txt")
    write(path, beads(count, width, depth))
    print(f"wrote {path}: {count} beads")


if __name__ == "__main__":
    main()
