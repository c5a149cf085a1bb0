"""Write a conical-hopper mesh (gmsh 2.2, hexahedra) like the LIGGGHTS peer's, and a particle file.

    .venv/bin/python tools/hopper_mesh.py cases/hopper [N]

Geometry (SI, the peer's: ../shared/peers/liggghts_hopper.sh): a cone from the orifice, radius
15 mm at z = 0, to radius 50 mm at half-angle 30° from vertical (z = 60.6 mm), then a cylinder of
radius 50 mm up to z = 0.30 m. Boundaries: "orifice" (z = 0), "top", "walls". Each cross-section
is an O-grid: a square lattice mapped onto the disk. Particles (d = 4 mm, ρ = 2500) sit on a
jittered cubic lattice in the cylinder (spacing 1.25 d: up to 11,000 of them), seeded.
"""
import sys
from pathlib import Path

import meshio
import numpy as np

ORIFICE, RADIUS, CONE_TOP, TOP = 0.015, 0.050, 0.0606, 0.30
DIAMETER, DENSITY = 0.004, 2500.0


def hopper_mesh(n_across=8, cone_levels=6, cylinder_levels=14):
    z = np.concatenate([np.linspace(0, CONE_TOP, cone_levels + 1), np.linspace(CONE_TOP, TOP, cylinder_levels + 1)[1:]])
    radius = np.where(z < CONE_TOP, ORIFICE + (RADIUS - ORIFICE) * z / CONE_TOP, RADIUS)
    s = np.linspace(-1, 1, n_across + 1)
    y, x = np.meshgrid(s, s, indexing="ij")
    disk = np.stack([x * np.sqrt(1 - y ** 2 / 2), y * np.sqrt(1 - x ** 2 / 2)], axis=-1).reshape(-1, 2)
    points = np.concatenate([np.column_stack([disk * r, np.full(len(disk), h)]) for r, h in zip(radius, z)])
    m = n_across + 1
    i, j, k = [a.ravel() for a in np.meshgrid(np.arange(n_across), np.arange(n_across), np.arange(len(z) - 1),
                                              indexing="ij")]
    v = lambda a, b, c: (k + c) * m * m + (j + b) * m + (i + a)
    hexes = np.stack([v(0, 0, 0), v(1, 0, 0), v(1, 1, 0), v(0, 1, 0), v(0, 0, 1), v(1, 0, 1), v(1, 1, 1), v(0, 1, 1)], 1)
    faces = hexes[:, [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]].reshape(-1, 4)
    keys, counts = np.unique(np.sort(faces, axis=1), axis=0, return_counts=True)
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    boundary = faces[first[counts == 1]]
    height = points[boundary][:, :, 2]
    tag = np.where(np.all(height == 0, axis=1), 1, np.where(np.all(height == TOP, axis=1), 2, 3))
    return meshio.Mesh(points, [("quad", boundary), ("hexahedron", hexes)],
                       cell_data={"gmsh:physical": [tag, np.full(len(hexes), 10)],
                                  "gmsh:geometrical": [tag, np.full(len(hexes), 10)]},
                       field_data={"orifice": np.array([1, 2]), "top": np.array([2, 2]), "walls": np.array([3, 2]),
                                   "hopper": np.array([10, 3])})


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
    meshio.write(str(folder / "hopper.msh"), hopper_mesh(), file_format="gmsh22", binary=False)
    xyz = particles(count)
    table = np.column_stack([xyz, np.full(len(xyz), DIAMETER / 2), np.full(len(xyz), DENSITY)])
    np.savetxt(folder / "particles.txt", table, header="x y z radius density", comments="", fmt="%.6g")
    print(f"wrote {folder / 'hopper.msh'} and {len(xyz)} particles in {folder / 'particles.txt'}")


if __name__ == "__main__":
    main()
