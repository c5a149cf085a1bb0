"""The serial mesh that rank 0 hands to PETSc: the cells of a box (hexahedra in PETSc's
lexicographic numbering, or each cut into 6 tetrahedra) and mesh files read with meshio (gmsh,
and every format meshio knows), with their named surfaces. ``pmpm.mesh`` distributes it."""
from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
from petsc4py import PETSc

from .errors import CaseError

VERTICES_PER_CELL = {"hex": 8, "tet": 4}
# meshio cell block names of the volume and surface elements pmpm reads
MESHIO_VOLUME = {"hexahedron": "hex", "tetra": "tet"}
MESHIO_SURFACE = ("triangle", "quad")
# the vertex order of meshio, VTK and gmsh against PETSc's: a permutation that is its own inverse,
# so it maps either order to the other
VTK_ORDER = {"hex": np.array([0, 3, 2, 1, 4, 5, 6, 7]), "tet": np.array([1, 0, 2, 3])}


def box_hexahedra(cells, serial) -> np.ndarray:
    """Vertices (PETSc order) of the hexahedra numbered ``serial`` in PETSc's lexicographic box."""
    nx, ny, _ = cells
    i, j, k = serial % nx, (serial // nx) % ny, serial // (nx * ny)
    corners = [(0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
    return np.stack([(i + a) + (nx + 1) * ((j + b) + (ny + 1) * (k + c)) for a, b, c in corners], axis=1)


def box_tetrahedra(lower, upper, cells):
    """Vertices and tetrahedra (PETSc order) of a box, each hexahedron cut into 6 (Kuhn)."""
    nx, ny, nz = cells
    axes = [np.linspace(lower[d], upper[d], n + 1) for d, n in enumerate(cells)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    xyz = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    i, j, k = [a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")]

    def vertex(di, dj, dk):
        return (i + di) + (nx + 1) * ((j + dj) + (ny + 1) * (k + dk))

    corner = {bits: vertex(*bits) for bits in np.ndindex(2, 2, 2)}
    # the 6 monotone paths from (0,0,0) to (1,1,1): one tetrahedron each, all sharing the diagonal
    paths = [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]
    tets = []
    for path in paths:
        step = [0, 0, 0]
        chain = [corner[(0, 0, 0)]]
        for axis in path:
            step[axis] = 1
            chain.append(corner[tuple(step)])
        tets.append(np.stack(chain, axis=1))
    tets = np.concatenate(tets)
    return xyz, orient_tetrahedra(xyz, tets)


def orient_tetrahedra(xyz, tets):
    """Swap two vertices where needed so every tetrahedron has PETSc's (negative) orientation."""
    p = xyz[tets]
    det = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    tets = tets.copy()
    flip = det > 0
    tets[flip, 0], tets[flip, 1] = tets[flip, 1], tets[flip, 0].copy()
    return tets


def cells_to_dmplex(comm, cells, xyz, cell_type):
    """Collective. An interpolated DMPlex of a cell list held on rank 0 (empty on the others)."""
    k = VERTICES_PER_CELL[cell_type]
    if comm.rank != 0:
        cells, xyz = np.zeros((0, k)), np.zeros((0, 3))
    return PETSc.DMPlex().createFromCellList(3, np.asarray(cells).astype(PETSc.IntType),
                                             np.asarray(xyz, float), interpolate=True, comm=comm)


def read_mesh_file(path: Path):
    """Rank 0. Read a mesh file with meshio.

    Returns (xyz, cells in PETSc order, cell type, (tagged face keys, their name index), names).
    """
    import meshio

    if path.is_dir():
        raise CaseError(f"{path}: is a folder, not a mesh file")
    if not path.is_file():
        raise CaseError(f"{path}: mesh file not found")
    chatter = io.StringIO()
    try:
        with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
            data = meshio.read(str(path))
    except (Exception, SystemExit) as exc:  # meshio raises many types (and may sys.exit) on a non-mesh
        detail = str(exc).splitlines()[0] if isinstance(exc, Exception) and str(exc) else "unknown or corrupt format"
        raise CaseError(f"{path}: not a mesh file meshio can read ({detail})") from None
    volume = [(MESHIO_VOLUME.get(block.type), block.data) for block in data.cells if block.type in MESHIO_VOLUME]
    others = sorted({block.type for block in data.cells} - set(MESHIO_VOLUME) - set(MESHIO_SURFACE)
                    - {"vertex", "line", "line3"})
    if not volume:
        raise CaseError(f"{path}: the mesh has no hexahedra or tetrahedra (cell types: "
                        f"{', '.join(sorted({b.type for b in data.cells})) or 'none'})")
    kinds = {kind for kind, _ in volume}
    if len(kinds) > 1 or others:
        raise CaseError(f"{path}: pmpm reads meshes of hexahedra only or tetrahedra only; this one has "
                        f"{', '.join(sorted(kinds | set(others)))}")
    cell_type = kinds.pop()
    cells = np.concatenate([block for _, block in volume]).astype(np.int64)
    # keep only the vertices the cells use, in file order
    used = np.zeros(len(data.points), bool)
    used[cells.ravel()] = True
    renumber = np.cumsum(used) - 1
    xyz = np.asarray(data.points, float)[used]
    if xyz.shape[1] == 2:
        raise CaseError(f"{path}: a 2-D mesh; pmpm needs a 3-D volume mesh")
    cells = renumber[cells][:, VTK_ORDER[cell_type]]
    if cell_type == "tet":
        cells = orient_tetrahedra(xyz, cells)
    # named surface elements (gmsh physical groups of dimension 2)
    names_of_tag = {int(tag): name for name, (tag, dim) in
                    ((n, v[:2]) for n, v in data.field_data.items()) if int(dim) == 2}
    physical = data.cell_data.get("gmsh:physical")
    keys, tags = [], []
    if physical is not None:
        for block, tag in zip(data.cells, physical):
            if block.type in MESHIO_SURFACE:
                surface = block.data.astype(np.int64)
                keep = used[surface].all(axis=1)
                keys.append(np.sort(renumber[surface[keep]], axis=1)[:, :3])
                tags.append(np.asarray(tag, np.int64)[keep])
    tag_list = sorted(set(np.concatenate(tags).tolist())) if tags else []
    names = [names_of_tag.get(tag, f"surface{tag}") for tag in tag_list]
    keys = np.concatenate(keys) if keys else np.zeros((0, 3), np.int64)
    tags = np.concatenate(tags) if tags else np.zeros(0, np.int64)
    name_index = np.searchsorted(np.array(tag_list, np.int64), tags)
    keys, first = np.unique(keys, axis=0, return_index=True)
    return xyz, cells, cell_type, (keys, name_index[first]), names
