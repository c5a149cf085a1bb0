"""Write vessel.msh, the paddle scene's mesh: an upright cylinder of liquid (radius 10 cm, 20 cm
high), hexahedra on an O-grid (a square lattice mapped onto each disc), about 8 mm cells: three
per particle diameter. Boundaries: "wall" around, "bottom", and "top" (open: the liquid the
particles displace leaves there).

    .venv/bin/python cases/paddle/make_mesh.py [cells across, default 24]
"""
import sys
from pathlib import Path

import numpy as np

from pmpm import meshgen

RADIUS, HEIGHT = 0.1, 0.2


def vessel(n_across: int):
    levels = int(round(n_across * HEIGHT / (2 * RADIUS)))

    def names(centre, normal, default):
        return np.select([default == "zmin", default == "zmax"], ["bottom", "top"], "wall")

    return meshgen.cylinder(RADIUS, np.linspace(0.0, HEIGHT, levels + 1), n_across, name=names)


if __name__ == "__main__":
    n_across = int(sys.argv[1]) if len(sys.argv) > 1 else 24
    path = Path(__file__).resolve().parent / "vessel.msh"
    meshgen.write(vessel(n_across), path)
    print(f"wrote {path}")
