"""Write a conical-hopper mesh (gmsh 2.2, hexahedra) like the LIGGGHTS peer's, and a particle file:
the geometry and the one-off fill of bench/hopper.py (cases/hopper has its own mesh script).

    .venv/bin/python tools/hopper_mesh.py FOLDER [N]

Geometry (SI, the peer's: ../shared/peers/liggghts_hopper.sh): a cone from the orifice, radius
15 mm at z = 0, to radius 50 mm at half-angle 30° from vertical (z = 60.6 mm), then a cylinder of
radius 50 mm up to z = 0.30 m. Boundaries: "orifice" (z = 0), "top", "walls". Each cross-section
is an O-grid: a square lattice mapped onto the disk. Particles (d = 4 mm, ρ = 2500) sit on a
jittered cubic lattice in the cylinder (spacing 1.25 d: up to 11,000 of them), seeded.
"""
import sys
from pathlib import Path

import numpy as np

from pmpm import meshgen

ORIFICE, RADIUS, CONE_TOP, TOP = 0.015, 0.050, 0.0606, 0.30
DIAMETER, DENSITY = 0.004, 2500.0


def hopper_mesh(n_across=8, cone_levels=6, cylinder_levels=14):
    z = np.concatenate([np.linspace(0, CONE_TOP, cone_levels + 1), np.linspace(CONE_TOP, TOP, cylinder_levels + 1)[1:]])
    radius = np.where(z < CONE_TOP, ORIFICE + (RADIUS - ORIFICE) * z / CONE_TOP, RADIUS)

    def names(centre, normal, default):
        return np.select([default == "zmin", default == "zmax"], ["orifice", "top"], "walls")

    return meshgen.cylinder(radius, z, n_across, name=names)


def particles(count, seed=1):
    """Centres on a jittered cubic lattice inside the cylinder (clear of the wall by one diameter)."""
    spacing = 1.25 * DIAMETER
    axis = np.arange(-RADIUS + DIAMETER, RADIUS - DIAMETER + 1e-12, spacing)
    layers = []
    z = CONE_TOP + DIAMETER
    while sum(len(l) for l in layers) < count and z < TOP - DIAMETER:
        x, y = np.meshgrid(axis, axis)
        keep = np.hypot(x, y) < RADIUS - 1.5 * DIAMETER
        layers.append(np.column_stack([x[keep], y[keep], np.full(keep.sum(), z)]))
        z += spacing
    xyz = np.concatenate(layers)[:count]
    if len(xyz) < count:
        raise SystemExit(f"only {len(xyz)} particles fit")
    rng = np.random.default_rng(seed)
    return xyz + rng.uniform(-0.2, 0.2, xyz.shape) * (spacing - DIAMETER)


def main():
    folder = Path(sys.argv[1])
    count = int(sys.argv[2]) if len(sys.argv) > 2 else 10000
    folder.mkdir(parents=True, exist_ok=True)
    meshgen.write(hopper_mesh(), folder / "hopper.msh")
    xyz = particles(count)
    table = np.column_stack([xyz, np.full(len(xyz), DIAMETER / 2), np.full(len(xyz), DENSITY)])
    np.savetxt(folder / "particles.txt", table, header="x y z radius density", comments="", fmt="%.6g")
    print(f"wrote {folder / 'hopper.msh'} and {len(xyz)} particles in {folder / 'particles.txt'}")


if __name__ == "__main__":
    main()
