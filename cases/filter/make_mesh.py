"""Write this case's mesh, filter.msh: a square pipe with a perforated plate across it, hexahedra
(gmsh 2.2) from pmpm.meshgen.

    .venv/bin/python cases/filter/make_mesh.py

The pipe runs along x, 36 cells long and 18 × 18 cells across, cells of H = 0.25 mm (9 × 4.5 ×
4.5 mm). The plate, two cells thick, stands across it 12 cells downstream of the inlet; its holes
are 3 × 3 squares of 4 × 4 cells (1 mm), the lowest row on the floor so that what settles can roll
through, with bars of 2 cells between them. Boundaries: "inlet" (x = 0), "outlet" (x = 9 mm),
"plate" (the plate's faces and its holes' sides), "walls" (the pipe's four sides).
"""
from pathlib import Path

import numpy as np

from pmpm import meshgen

H = 0.25e-3                        # cell size (m)
LENGTH, SIDE = 36, 18              # cells
PLATE_START, PLATE_CELLS = 12, 2   # cells from the inlet, thickness
HOLE, BAR = 4, 2                   # cells
PLATE_X = (PLATE_START * H, (PLATE_START + PLATE_CELLS) * H)


def in_hole(index):
    """Whether cell row/column ``index`` (0 at the floor or the side) lies in a hole: from 0, holes
    of HOLE cells after bars of BAR (the last bar at the top or far side takes what is left)."""
    return (index % (HOLE + BAR) < HOLE) & (index < 3 * (HOLE + BAR))


def plate(centre):
    x, j, k = centre[:, 0], np.floor(centre[:, 1] / H).astype(int), np.floor(centre[:, 2] / H).astype(int)
    across = (x > PLATE_X[0]) & (x < PLATE_X[1])
    return across & ~(in_hole(j - 1) & in_hole(k))     # one cell of bar at each side, none at the floor


def names(centre, normal, default):
    return np.select([default == "xmin", default == "xmax", default == "solid"], ["inlet", "outlet", "plate"],
                     "walls")


def filter_mesh():
    x = np.arange(LENGTH + 1) * H
    across = np.arange(SIDE + 1) * H
    return meshgen.block(x, across, across, solid=plate, name=names)


if __name__ == "__main__":
    path = Path(__file__).with_name("filter.msh")
    meshgen.write(filter_mesh(), path)
    print(f"wrote {path}")
