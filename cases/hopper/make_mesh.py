"""Write this case's mesh, hopper.msh: a conical hopper of hexahedra (gmsh 2.2), from pmpm.meshgen.

    .venv/bin/python cases/hopper/make_mesh.py

A cone of half-angle 45° from the orifice (radius 15 mm, at z = 0) to radius 50 mm (z = 35 mm),
then a cylinder of radius 50 mm up to z = 0.20 m. Boundaries: "orifice" (z = 0), "top", "walls".
The 45° cone is taken as no steeper than the stagnant zone a flat-bottomed bin forms, so that
Beverloo's law for flat-bottomed bins applies to it unchanged (pmpm.reference.beverloo_mass_rate);
a steeper cone discharges faster: in a trial run the 30° cone of tools/hopper_mesh.py passed
1.16 × Beverloo's rate, this one 0.94 ×.
"""
from pathlib import Path

import numpy as np

from pmpm import meshgen

ORIFICE, RADIUS, TOP = 0.015, 0.050, 0.20
CONE_TOP = RADIUS - ORIFICE          # 45°: the radius grows as fast as the height


def hopper(n_across=8, cone_levels=5, cylinder_levels=12):
    z = np.concatenate([np.linspace(0, CONE_TOP, cone_levels + 1), np.linspace(CONE_TOP, TOP, cylinder_levels + 1)[1:]])
    radius = np.minimum(ORIFICE + z, RADIUS)

    def names(centre, normal, default):
        return np.select([default == "zmin", default == "zmax"], ["orifice", "top"], "walls")

    return meshgen.cylinder(radius, z, n_across, name=names)


if __name__ == "__main__":
    path = Path(__file__).with_name("hopper.msh")
    meshgen.write(hopper(), path)
    print(f"wrote {path}")
