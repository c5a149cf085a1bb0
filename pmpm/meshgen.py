"""Hexahedral meshes for case folders' mesh scripts: blocks with cut-outs and named boundary
patches, and O-grid cylinders (a vessel, a pipe, a hopper), written as gmsh files that
``[mesh] file`` reads with their boundary names.

    from pmpm import meshgen
    mesh = meshgen.block(x, y, z, solid=lambda c: ..., name=lambda centre, normal, default: ...)
    meshgen.write(mesh, "box.msh")

Boundary faces are named ``xmin`` … ``zmax`` by the side of the block they lie on, ``solid``
where a cut-out cell was, unless the ``name`` function says otherwise (an inlet patch on part of
a side, the holes of a plate).
"""
from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np

SIDES = ("xmin", "xmax", "ymin", "ymax", "zmin", "zmax")
# a hexahedron's faces in gmsh/VTK vertex order, each wound outwards
HEX_FACES = np.array([[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]])


def block(x, y, z, solid=None, name=None) -> meshio.Mesh:
    """A block of hexahedra on the grid lines ``x``, ``y``, ``z`` (increasing, m).

    Parameters
    ----------
    solid : function of the cell centres (n, 3) → bool (n,): cells left out (a plate, an obstacle)
    name : function (face centres (k, 3), outward normals (k, 3), default names (k,)) → names (k,),
        to rename boundary faces (patches)
    """
    x, y, z = (np.asarray(a, float) for a in (x, y, z))
    nx, ny, nz = len(x) - 1, len(y) - 1, len(z) - 1
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    points = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
    k, j, i = (a.ravel() for a in np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij"))

    def vertex(a, b, c):
        return ((k + c) * (ny + 1) + (j + b)) * (nx + 1) + (i + a)

    hexes = np.stack([vertex(0, 0, 0), vertex(1, 0, 0), vertex(1, 1, 0), vertex(0, 1, 0),
                      vertex(0, 0, 1), vertex(1, 0, 1), vertex(1, 1, 1), vertex(0, 1, 1)], axis=1)
    if solid is not None:
        hexes = hexes[~np.asarray(solid(points[hexes].mean(axis=1)), bool)]
    return hex_mesh(points, hexes, name, lower=np.array([x[0], y[0], z[0]]), upper=np.array([x[-1], y[-1], z[-1]]))


def cylinder(radius, z, n_across: int = 8, name=None) -> meshio.Mesh:
    """An O-grid cylinder about the z axis: a square lattice of ``n_across`` × ``n_across`` cells
    mapped onto each disc, on the levels ``z`` (m), of radius ``radius`` (a number, or one per
    level: a cone, a hopper). Boundary faces: ``zmin``, ``zmax``, and ``wall`` around, unless
    ``name`` (as for ``block``) says otherwise."""
    z = np.asarray(z, float)
    radius = np.broadcast_to(np.asarray(radius, float), z.shape)
    s = np.linspace(-1, 1, n_across + 1)
    b, a = np.meshgrid(s, s, indexing="ij")
    disc = np.stack([a * np.sqrt(1 - b ** 2 / 2), b * np.sqrt(1 - a ** 2 / 2)], axis=-1).reshape(-1, 2)
    points = np.concatenate([np.column_stack([disc * r, np.full(len(disc), h)]) for r, h in zip(radius, z)])
    m = n_across + 1
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(n_across), np.arange(n_across), np.arange(len(z) - 1),
                                              indexing="ij"))

    def vertex(a, b, c):
        return (k + c) * m * m + (j + b) * m + (i + a)

    hexes = np.stack([vertex(0, 0, 0), vertex(1, 0, 0), vertex(1, 1, 0), vertex(0, 1, 0),
                      vertex(0, 0, 1), vertex(1, 0, 1), vertex(1, 1, 1), vertex(0, 1, 1)], axis=1)

    def around(centre, normal, default):
        names = np.where(default == "zmin", "zmin", np.where(default == "zmax", "zmax", "wall"))
        return names if name is None else name(centre, normal, names)

    return hex_mesh(points, hexes, around, lower=np.array([0, 0, z[0]]), upper=np.array([0, 0, z[-1]]))


def hex_mesh(points, hexes, name, lower, upper) -> meshio.Mesh:
    """The mesh of these hexahedra with its boundary quads named (see ``block``)."""
    faces = hexes[:, HEX_FACES].reshape(-1, 4)
    key = np.sort(faces, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    boundary = faces[first[counts == 1]]
    corners = points[boundary]
    centre = corners.mean(axis=1)
    normal = np.cross(corners[:, 2] - corners[:, 0], corners[:, 3] - corners[:, 1])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    default = np.full(len(boundary), "solid", dtype=object)
    extent = np.maximum(upper - lower, 1e-300)
    for axis in range(3):
        if upper[axis] > lower[axis]:
            default[np.abs(centre[:, axis] - lower[axis]) < 1e-9 * extent[axis]] = SIDES[2 * axis]
            default[np.abs(centre[:, axis] - upper[axis]) < 1e-9 * extent[axis]] = SIDES[2 * axis + 1]
    names = np.asarray(default if name is None else name(centre, normal, default), dtype=object)
    unique = sorted(set(names.tolist()))
    tag = np.array([unique.index(n) + 1 for n in names])
    volume_tag = len(unique) + 1
    field_data = {n: np.array([t + 1, 2]) for t, n in enumerate(unique)}
    field_data["fluid"] = np.array([volume_tag, 3])
    return meshio.Mesh(points, [("quad", boundary), ("hexahedron", hexes)],
                       cell_data={"gmsh:physical": [tag, np.full(len(hexes), volume_tag)],
                                  "gmsh:geometrical": [tag, np.full(len(hexes), volume_tag)]},
                       field_data=field_data)


def write(mesh: meshio.Mesh, path) -> None:
    """Write ``mesh`` as a gmsh 2.2 file (what ``[mesh] file`` reads, with its boundary names)."""
    unused = np.setdiff1d(np.arange(len(mesh.points)), np.concatenate([c.data.ravel() for c in mesh.cells]))
    if len(unused):   # points of cut-out cells only: drop them, renumber
        keep = np.ones(len(mesh.points), bool)
        keep[unused] = False
        new = np.cumsum(keep) - 1
        mesh = meshio.Mesh(mesh.points[keep], [(c.type, new[c.data]) for c in mesh.cells], cell_data=mesh.cell_data,
                           field_data=mesh.field_data)
    meshio.write(str(Path(path)), mesh, file_format="gmsh22", binary=False)
