"""The finite-volume mesh: made or read once, distributed by DMPlex, then flat numpy arrays.

DMPlex does what it is good at: partitioning (ptscotch), ``distribute(overlap=1)`` with finite-volume
adjacency (one layer of face-neighbour ghost cells), and the star forests that say which local
point is a copy of which remote one. Everything the time loop touches is built here, once, as
numpy arrays over the whole rank: no per-cell or per-face petsc4py call after
construction. The field contract is the table in ARCHITECTURE.md.

Local numbering: owned cells ``[0, n_owned_cells)``, ghost cells after them. Faces hold every face
with at least one owned cell, interior faces first (owner < neighbour, so the owner is always an
owned cell), then domain-boundary faces. Area vectors point from ``face_cells[:, 0]`` to
``face_cells[:, 1]``, outward on the boundary.
"""
from __future__ import annotations

import time as wallclock
from pathlib import Path

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from .arrays import summed
from .errors import CaseError
from .parallel import agree, allreduce_sum
from .cell_bins import CellBins, holding_cells
from .partition import set_coordinate_partition
from .serial_mesh import VERTICES_PER_CELL, box_hexahedra, box_tetrahedra, cells_to_dmplex, read_mesh_file

BOX_BOUNDARIES = ("xmin", "xmax", "ymin", "ymax", "zmin", "zmax")
UNNAMED_BOUNDARY = "boundary"
# Faces of a cell as local vertex indices, PETSc vertex order. Orientation is fixed
# geometrically afterwards, so only the grouping into faces matters here.
CELL_FACES = {
    "hex": np.array([(0, 1, 2, 3), (4, 5, 6, 7), (0, 3, 5, 4), (1, 7, 6, 2), (3, 2, 6, 5), (0, 4, 7, 1)]),
    "tet": np.array([(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)]),
}


class Mesh:
    """A distributed mesh as read-only numpy arrays. Build with :meth:`from_box` or :meth:`from_file`."""

    # -- construction -----------------------------------------------------------------------------
    @classmethod
    def from_box(cls, comm, lower, upper, cells, cell_type: str = "hex", patches=(), work=None) -> "Mesh":
        """Collective. A box of ``cells`` = (nx, ny, nz) hexahedra, or 6 tetrahedra per hexahedron.

        Boundaries are named xmin xmax ymin ymax zmin zmax, and ``patches`` (name, side, lower,
        upper) rename the faces of a side whose centres lie in the box [lower, upper] (an inlet on
        part of a side; later patches win). ``work`` (points (m, 3), amounts (m,)), on rank 0: work
        besides the cells' that the partition shares out too (``pmpm.partition``).
        """
        lower, upper = np.asarray(lower, float), np.asarray(upper, float)
        cells = [int(n) for n in cells]
        start = wallclock.perf_counter()
        if cell_type == "hex":
            # PETSc's own generator interpolates far faster than createFromCellList;
            # it numbers cells and vertices lexicographically (checked on a sample below)
            dm = PETSc.DMPlex().createBoxMesh(cells, lower=tuple(lower), upper=tuple(upper), simplex=False,
                                              interpolate=True, comm=comm)
            serial_vertices = lambda serial: box_hexahedra(cells, serial)
        else:
            xyz, tets = box_tetrahedra(lower, upper, cells) if comm.rank == 0 else (None, None)
            dm = cells_to_dmplex(comm, tets, xyz, "tet")
            tets = comm.bcast(tets, root=0)
            serial_vertices = lambda serial: tets[serial]

        def name_box_faces(mesh, faces):
            centers = mesh.face_center[faces]
            extent = upper - lower
            index = np.full(len(centers), -1, np.int64)
            for axis in range(3):
                tolerance = 1e-9 * extent[axis]
                index[np.abs(centers[:, axis] - lower[axis]) < tolerance] = 2 * axis
                index[np.abs(centers[:, axis] - upper[axis]) < tolerance] = 2 * axis + 1
            names = list(BOX_BOUNDARIES)
            for name, side, low, high in patches:
                if name not in names:
                    names.append(name)
                on = (index == BOX_BOUNDARIES.index(side)) & np.all((centers >= low) & (centers <= high), axis=1)
                index[on] = names.index(name)
            return index, names

        mesh = cls(comm, dm, cell_type, serial_vertices, name_box_faces, start, work)
        mesh.source = (f"box {'×'.join(map(str, cells))} {cell_type}, "
                       f"[{', '.join(f'{v:g}' for v in lower)}] to [{', '.join(f'{v:g}' for v in upper)}] m")
        return mesh

    @classmethod
    def from_file(cls, comm, path: Path, work=None) -> "Mesh":
        """Collective. A mesh file (gmsh .msh, or any volume format meshio reads), read on rank 0.

        Hexahedra or tetrahedra (not mixed). Boundary faces are named by the file's 2-D physical
        groups (gmsh) where it has them; other boundary faces are named "boundary". ``work``: as
        in :meth:`from_box`.
        """
        start = wallclock.perf_counter()
        read = None
        error = None
        if comm.rank == 0:
            try:
                read = read_mesh_file(Path(path))
            except CaseError as exc:
                error = exc
        agree(comm, error)
        xyz, serial_cells, cell_type, tagged_faces, tag_names = read if comm.rank == 0 else (None,) * 5
        cell_type = comm.bcast(cell_type, root=0)
        dm = cells_to_dmplex(comm, serial_cells, xyz, cell_type)
        serial_cells, tagged_faces, tag_names = comm.bcast((serial_cells, tagged_faces, tag_names), root=0)
        serial_vertices = lambda serial: serial_cells[serial]

        def name_file_faces(mesh, faces):
            # a boundary face is found in the file's list of tagged faces by its sorted vertex ids
            keys = np.sort(mesh.vertex_serial[mesh.face_vertices[faces]], axis=1)[:, :3]
            where = match_rows(keys, tagged_faces[0])
            # a file without named surfaces (e.g. only a volume group): every face is "boundary"
            tagged = tagged_faces[1][np.maximum(where, 0)] if len(tagged_faces[1]) else np.zeros(len(where), np.int64)
            index = np.where(where >= 0, tagged, len(tag_names))
            names = tag_names + [UNNAMED_BOUNDARY]
            # drop names no face carries (collectively, so every rank keeps the same list)
            used = np.zeros(len(names), np.int64)
            used[np.unique(index)] = 1
            comm.Allreduce(MPI.IN_PLACE, used, op=MPI.SUM)
            used = used > 0
            renumber = np.cumsum(used) - 1
            return renumber[index], [n for n, u in zip(names, used) if u]

        mesh = cls(comm, dm, cell_type, serial_vertices, name_file_faces, start, work)
        mesh.source = f"file {Path(path).name} ({cell_type})"
        return mesh

    def __init__(self, comm, dm, cell_type, serial_vertices, name_boundary_faces, start_time, work=None):
        """Collective. Distribute ``dm`` and build the arrays (use the ``from_*`` constructors).

        ``serial_vertices(serial cell numbers)`` gives those cells' vertices in the undistributed
        mesh, PETSc order; ``name_boundary_faces(mesh, faces)`` gives the boundary index of each of
        the domain-boundary faces ``faces`` and the list of boundary names (collective).
        """
        self.comm = comm
        self.cell_type = cell_type
        self.source = ""
        n_global_cells = comm.bcast(dm.getHeightStratum(0)[1] if comm.rank == 0 else None, root=0)
        serial_vertex_start = comm.bcast(dm.getDepthStratum(0)[0] if comm.rank == 0 else None, root=0)
        dm.setBasicAdjacency(True, False)  # finite-volume adjacency: the overlap is the face neighbours
        self.build_stages = {"create": wallclock.perf_counter() - start_time}
        mark = wallclock.perf_counter()
        # each rank's box, [lower, upper) (2, ranks, 3), outer sides at ±inf: it holds the centres of
        # the rank's cells, and particles in a flow belong to the rank whose box holds their centre
        self.part_boxes = np.stack([np.full((1, 3), -np.inf), np.full((1, 3), np.inf)])
        if comm.size > 1:   # partitioned by coordinates, on rank 0: the same partition in every run
            centres = None
            if comm.rank == 0:
                xyz = dm.getCoordinatesLocal().getArray().reshape(-1, 3)
                centres = xyz[serial_vertices(np.arange(n_global_cells))].mean(axis=1)
            self.part_boxes = set_coordinate_partition(dm, comm, centres,
                                                       *(work if comm.rank == 0 and work is not None else ()))
        migration = dm.distribute(overlap=1) if comm.size > 1 else None
        self.build_stages["distribute"] = wallclock.perf_counter() - mark
        mark = wallclock.perf_counter()
        cell_start, cell_end = dm.getHeightStratum(0)
        vertex_start, vertex_end = dm.getDepthStratum(0)
        n_local = cell_end - cell_start

        # serial (undistributed) numbers of the local cells and vertices
        if migration is not None:
            serial_point = migration.getGraph()[2][:, 1]
            self.cell_serial = serial_point[cell_start:cell_end].astype(np.int64)
            self.vertex_serial = (serial_point[vertex_start:vertex_end] - serial_vertex_start).astype(np.int64)
        else:
            self.cell_serial = np.arange(n_local, dtype=np.int64)
            self.vertex_serial = np.arange(vertex_end - vertex_start, dtype=np.int64)

        # owned cells first, then ghosts (DMPlex numbers them so; asserted here)
        numbering = dm.getCellNumbering().getIndices()
        owned = numbering >= 0
        self.n_owned_cells = int(owned.sum())
        if not owned[:self.n_owned_cells].all():
            raise RuntimeError("DMPlex did not number the owned cells before the overlap cells")
        self.n_local_cells = int(n_local)
        self.n_global_cells = int(n_global_cells)
        self.cell_gid = np.where(owned, numbering, -numbering - 1).astype(np.int64)

        self.vertex_xyz = dm.getCoordinatesLocal().getArray().reshape(-1, 3).copy()
        self.vertex_owned = np.ones(vertex_end - vertex_start, bool)
        self._cell_sf = None
        if comm.size > 1:
            _, leaves, remote = dm.getPointSF().getGraph()
            in_vertices = (leaves >= vertex_start) & (leaves < vertex_end)
            self.vertex_owned[leaves[in_vertices] - vertex_start] = False
            in_cells = (leaves >= cell_start) & (leaves < cell_end)
            self._cell_sf = PETSc.SF().create(comm=comm)
            self._cell_sf.setGraph(n_local, leaves[in_cells].astype(PETSc.IntType),
                                   remote[in_cells].astype(PETSc.IntType))
            self._cell_sf.setUp()
        self._mpi_types = {}

        # cell → vertex, PETSc vertex order: the serial cell list mapped through the migration SF
        local_of_serial = np.full(int(self.vertex_serial.max(initial=-1)) + 1, -1, np.int64)
        local_of_serial[self.vertex_serial] = np.arange(len(self.vertex_serial))
        cell_vertices = local_of_serial[serial_vertices(self.cell_serial)]
        k = VERTICES_PER_CELL[cell_type]
        sample = np.unique(np.linspace(0, n_local - 1, min(n_local, 64)).astype(np.int64))
        closure = np.array([dm.getTransitiveClosure(c + cell_start)[0][-k:] for c in sample]).reshape(-1, k)
        if not np.array_equal(np.sort(closure - vertex_start, axis=1), np.sort(cell_vertices[sample], axis=1)):
            # not the numbering assumed: ask DMPlex for every cell (slow: one call per cell)
            cell_vertices = np.array([dm.getTransitiveClosure(c)[0][-k:] for c in range(cell_start, cell_end)],
                                     dtype=np.int64).reshape(n_local, k) - vertex_start
        self.cell_vertices = cell_vertices
        # the rest is built from these arrays: the DMPlex goes now, before the faces' temporaries
        dm.destroy()
        self.build_stages["cells"] = wallclock.perf_counter() - mark
        mark = wallclock.perf_counter()
        self._build_faces_and_geometry()
        self.build_stages["faces and geometry"] = wallclock.perf_counter() - mark

        # boundary names
        boundary = np.flatnonzero(self.face_cells[:, 1] < 0)
        index, self.boundary_names = name_boundary_faces(self, boundary)
        if (index < 0).any():
            raise RuntimeError("a boundary face could not be named")
        self.face_boundary = np.full(len(self.face_cells), -1, np.int64)
        self.face_boundary[boundary] = index

        self.lower, self.upper = np.empty(3), np.empty(3)
        comm.Allreduce(self.vertex_xyz.min(axis=0, initial=np.inf), self.lower, op=MPI.MIN)
        comm.Allreduce(self.vertex_xyz.max(axis=0, initial=-np.inf), self.upper, op=MPI.MAX)
        self._center_bins = None
        self.build_seconds = comm.allreduce(wallclock.perf_counter() - start_time, op=MPI.MAX)

    def _build_faces_and_geometry(self):
        """Faces by hashing the cells' faces, then areas, volumes and centroids."""
        xyz, cv = self.vertex_xyz, self.cell_vertices
        pattern = CELL_FACES[self.cell_type]
        n_local, n_per_cell = len(cv), len(pattern)
        fv = cv[:, pattern].reshape(n_local * n_per_cell, -1)        # every cell's faces
        face_cell = np.repeat(np.arange(n_local), n_per_cell)
        # corner by corner, never a (faces, corners, 3) array: this is the peak of the mesh's memory
        corners = fv.shape[1]
        if corners == 3:
            area_vec = 0.5 * np.cross(xyz[fv[:, 1]] - xyz[fv[:, 0]], xyz[fv[:, 2]] - xyz[fv[:, 0]])
        else:
            area_vec = 0.5 * np.cross(xyz[fv[:, 2]] - xyz[fv[:, 0]], xyz[fv[:, 3]] - xyz[fv[:, 1]])
        center = mean_of_gathers(xyz, fv)
        cell_mean = mean_of_gathers(xyz, cv)
        arm = center - cell_mean[face_cell]                             # apex → face centre
        # orient each cell's faces outward
        outward = np.einsum("ij,ij->i", area_vec, arm) >= 0
        area_vec[~outward] *= -1
        fv[~outward] = fv[~outward][:, ::-1]
        # volume and centroid from pyramids on the faces, apex at the vertex mean
        pyramid = np.einsum("ij,ij->i", arm, area_vec) / 3.0
        volume = np.bincount(face_cell, pyramid, minlength=n_local)
        offset = np.stack([np.bincount(face_cell, 0.75 * pyramid * arm[:, d], minlength=n_local) for d in range(3)],
                          axis=1)
        del arm
        error = None
        if (volume <= 0).any():
            bad = int(np.argmax(volume <= 0))
            error = CaseError(f"mesh: cell {self.cell_serial[bad]} has volume {volume[bad]:.3g} m³ (inverted or degenerate)")
        agree(self.comm, error)
        self.cell_volume = volume
        self.cell_center = cell_mean + offset / volume[:, None]

        # pair equal faces: the same 3 smallest vertex numbers
        first, second, single = pair_equal_rows(np.sort(fv, axis=1)[:, :3])
        n_owned = self.n_owned_cells
        owner, neighbour = face_cell[first], face_cell[second]
        swap = neighbour < owner
        first[swap], second[swap] = second[swap], first[swap]
        owner, neighbour = np.minimum(owner, neighbour), np.maximum(owner, neighbour)
        keep = owner < n_owned
        first, owner, neighbour = first[keep], owner[keep], neighbour[keep]
        order = np.lexsort((neighbour, owner))
        first, owner, neighbour = first[order], owner[order], neighbour[order]
        single = single[face_cell[single] < n_owned]          # domain boundary of owned cells
        single = single[np.argsort(face_cell[single], kind="stable")]
        rows = np.concatenate([first, single])
        self.n_interior_faces = len(first)
        self.face_cells = np.concatenate([np.stack([owner, neighbour], axis=1),
                                          np.stack([face_cell[single], np.full(len(single), -1)], axis=1)])
        self.face_vertices = fv[rows]
        self.face_area_vec = area_vec[rows]
        self.face_area = np.linalg.norm(self.face_area_vec, axis=1)
        self.face_center = center[rows]

    # -- halo -------------------------------------------------------------------------------------
    def _unit(self, array):
        width = int(np.prod(array.shape[1:], dtype=int))
        base = MPI._typedict[array.dtype.char]
        key = (base.handle if hasattr(base, "handle") else id(base), width)
        if key not in self._mpi_types:
            self._mpi_types[key] = base.Create_contiguous(width).Commit() if width > 1 else base
        return self._mpi_types[key]

    def update_ghosts(self, array: np.ndarray) -> np.ndarray:
        """Collective. Copy each owner's rows into its ghost copies, in place; returns ``array``."""
        if self._cell_sf is not None:
            array = np.ascontiguousarray(array)
            unit = self._unit(array)
            self._cell_sf.bcastBegin(unit, array, array, MPI.REPLACE)
            self._cell_sf.bcastEnd(unit, array, array, MPI.REPLACE)
        return array

    def add_ghosts_to_owners(self, array: np.ndarray) -> np.ndarray:
        """Collective. Add every ghost row into its owner's row, in place (ghost rows keep their values)."""
        if self._cell_sf is not None:
            unit = self._unit(array)
            self._cell_sf.reduceBegin(unit, array, array, MPI.SUM)
            self._cell_sf.reduceEnd(unit, array, array, MPI.SUM)
        return array

    # -- queries ----------------------------------------------------------------------------------
    def find_owned_cells(self, points: np.ndarray) -> np.ndarray:
        """Local. The owned cell holding each point (n, 3), or -1 where no owned cell holds it.

        Candidates are the owned cells whose centres lie within the largest circumradius of the
        point, found through a lattice of bins over the centres; the nearest is tested first (it
        holds the point on regular meshes). Tests use the face planes (cells are convex), so a
        point on a shared face goes to the first candidate that holds it (``pmpm.cell_bins``).
        """
        points = np.asarray(points, float).reshape(-1, 3)
        if self.n_owned_cells == 0 or len(points) == 0:
            return np.full(len(points), -1, np.int64)
        if self._center_bins is None:
            owned = slice(0, self.n_owned_cells)
            self._center_bins = CellBins(self.cell_center[owned], float(np.median(self.cell_volume[owned])) ** (1 / 3))
            reach = self.vertex_xyz[self.cell_vertices[owned]] - self.cell_center[owned, None, :]
            self._circumradius = float(np.sqrt(np.einsum("cvd,cvd->cv", reach, reach).max()))
        bins = self._center_bins
        return holding_cells(self.vertex_xyz, self.cell_vertices, CELL_FACES[self.cell_type], self.cell_center,
                             self._circumradius * (1 + 1e-9), bins.lower, bins.width, bins.counts, bins.start,
                             bins.cells, points)

    def inside_domain(self, points: np.ndarray) -> np.ndarray:
        """Collective. (n,) bool: the point lies in some rank's owned cells."""
        found = (self.find_owned_cells(points) >= 0).astype(np.int64)
        return allreduce_sum(self.comm, found) > 0

    def boundary_triangles(self, names) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Collective. Every triangle of the named boundaries, the same on every rank.

        Returns
        -------
        triangles : (m, 3, 3) float — vertex coordinates (quads split in two)
        boundary : (m,) int64 — index into ``boundary_names``
        normal : (m, 3) float — unit normal pointing into the domain
        """
        wanted = [self.boundary_names.index(n) for n in names]
        faces = np.flatnonzero(np.isin(self.face_boundary, wanted))
        fv = self.face_vertices[faces]
        split = [(0, 1, 2)] if fv.shape[1] == 3 else [(0, 1, 2), (0, 2, 3)]
        tri_vertices = np.concatenate([fv[:, list(t)] for t in split])
        parent = np.concatenate([faces] * len(split))
        part = np.repeat(np.arange(len(split)), len(faces))
        # an order independent of the rank count: by the face's serial vertex numbers
        key = np.sort(self.vertex_serial[self.face_vertices[parent]], axis=1)
        rows = (self.vertex_xyz[tri_vertices].reshape(-1, 9), self.face_boundary[parent],
                -self.face_area_vec[parent] / self.face_area[parent, None], np.column_stack([key, part]))
        gathered = [np.concatenate(chunks) for chunks in zip(*self.comm.allgather(rows))]
        triangles, boundary, normal, key = gathered
        order = np.lexsort(key.T[::-1])
        return triangles[order].reshape(-1, 3, 3), boundary[order].astype(np.int64), normal[order]

    def boundary_area(self) -> dict:
        """Collective. Total area of each named boundary (m²)."""
        on = self.face_boundary >= 0    # (a rank may hold no boundary face)
        area = summed(self.face_boundary[on], self.face_area[on], len(self.boundary_names))
        self.comm.Allreduce(MPI.IN_PLACE, area, op=MPI.SUM)
        return dict(zip(self.boundary_names, area.tolist()))

    def describe(self) -> str:
        """Collective. One line: size, type, boundaries, partition balance, build time."""
        owned = self.comm.allgather(self.n_owned_cells)
        ghosts = self.comm.allgather(self.n_local_cells - self.n_owned_cells)
        balance = f", {min(owned)}–{max(owned)} cells/rank + {max(ghosts)} ghosts" if self.comm.size > 1 else ""
        return (f"{self.n_global_cells} cells, {self.source}; boundaries {' '.join(self.boundary_names)}"
                f"{balance}; built in {self.build_seconds:.2f} s")


# -- building blocks ------------------------------------------------------------------------------
def mean_of_gathers(xyz: np.ndarray, index: np.ndarray) -> np.ndarray:
    """xyz[index].mean(axis=1) for index (m, k), without the (m, k, 3) temporary."""
    total = xyz[index[:, 0]]
    for k in range(1, index.shape[1]):
        total += xyz[index[:, k]]
    return total / index.shape[1]


def _packed_key(rows: np.ndarray):
    """One int64 per row of a non-negative int array, equal exactly where the rows are; None when
    the row does not fit in 63 bits."""
    width = rows.shape[1]
    bits = max(int(rows.max(initial=0)).bit_length(), 1)
    if bits * width > 63:
        return None
    key = np.zeros(len(rows), np.int64)
    for column in range(width):
        key <<= bits
        key |= rows[:, column]
    return key


def _row_order(rows: np.ndarray) -> np.ndarray:
    """Sorting permutation of the rows of a non-negative int array (one packed key when it fits)."""
    key = _packed_key(rows)
    if key is not None:
        return np.argsort(key, kind="stable")
    return np.lexsort(rows.T[::-1])


def pair_equal_rows(rows: np.ndarray):
    """Rows that occur twice and once. Returns (first, second, single) row indices."""
    key = _packed_key(rows)
    if key is not None:  # compare the sorted keys, not a sorted copy of the rows (memory)
        order = np.argsort(key, kind="stable")
        ordered = key[order]
        del key
        same = ordered[1:] == ordered[:-1]
    else:
        order = np.lexsort(rows.T[::-1])
        ordered = rows[order]
        same = (ordered[1:] == ordered[:-1]).all(axis=1)
    del ordered
    first = np.flatnonzero(same)
    paired = np.zeros(len(rows), bool)
    paired[first] = paired[first + 1] = True
    return order[first], order[first + 1], order[~paired]


def match_rows(rows: np.ndarray, table: np.ndarray) -> np.ndarray:
    """For each row, the index of the equal row in ``table`` (unique rows), or -1."""
    if len(table) == 0 or len(rows) == 0:
        return np.full(len(rows), -1, np.int64)
    both = np.concatenate([table, rows]).astype(np.int64)
    order = _row_order(both)
    ordered = both[order]
    same = np.concatenate([(ordered[1:] == ordered[:-1]).all(axis=1), [False]])
    result = np.full(len(both), -1, np.int64)
    # a table row directly followed by an equal query row (stable sort keeps table rows first)
    hit = same & (order < len(table))
    result[order[np.flatnonzero(hit) + 1]] = order[hit]
    return result[len(table):]
