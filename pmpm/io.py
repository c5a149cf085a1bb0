"""Outputs (README, "Outputs"): particles.csv, fields.h5 + fields.xdmf, checkpoint.h5, summary.json.

Field files are written collectively with parallel HDF5. Cells and vertices are stored in the
order of the undistributed mesh (``Mesh.cell_serial``), so the same case writes the same file on
any number of ranks: each rank sends its owned rows to the rank that writes that slab of the
serial order (one Alltoallv), then every rank writes one contiguous slab.

Cell connectivity is stored in VTK/XDMF vertex order (ParaView opens ``fields.xdmf``).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

os.environ.setdefault("H5PY_ALWAYS_USE_MPI", "1")  # Debian's h5py loads its MPI build only then
import h5py  # noqa: E402

from .errors import CaseError  # noqa: E402
from .serial_mesh import VTK_ORDER  # noqa: E402
from .ownership import gather_with  # noqa: E402
from .parallel import agree  # noqa: E402

XDMF_TOPOLOGY = {"hex": "Hexahedron", "tet": "Tetrahedron"}
RESULT_FILES = ("particles.csv", "fields.h5", "fields.xdmf", "summary.json", "checkpoint.h5", "bodies.csv")
# partial writes an interrupted run leaves (the files above are replaced from them atomically)
LEFTOVER_FILES = ("checkpoint.h5.tmp", "summary.json.tmp", "fields.xdmf.tmp")


def output_folder_problem(folder: Path) -> str | None:
    """Why ``folder`` may not take a run's results, or None (not collective; rank 0 asks).

    A new or empty folder takes them, and so does a folder of pmpm's own earlier results, which
    is renamed to keep them; a folder holding anything else (a case, meshes, notes, other folders)
    is never renamed or written into, nor is the current folder.
    """
    if folder.exists() and not folder.is_dir():
        return "is a file, not a folder"
    if not folder.is_dir():
        return None
    entries = list(folder.iterdir())
    foreign = sorted(e.name for e in entries if e.name not in RESULT_FILES + LEFTOVER_FILES or not e.is_file())
    if foreign:
        shown = ", ".join(foreign[:3]) + (", …" if len(foreign) > 3 else "")
        return (f"holds other things than pmpm's results ({shown}); pmpm writes into a new or empty folder, or "
                "renames a folder of its own earlier results to keep them: name another folder with --output")
    if any((folder / f).exists() for f in RESULT_FILES) and folder.resolve() == Path.cwd().resolve():
        return ("holds earlier results and is the current folder, which pmpm does not rename: name another "
                "folder with --output")
    return None


def prepare_output_folder(comm, folder: Path, keep_existing: bool = False) -> Path | None:
    """Collective. Make the output folder; an earlier run's results are kept, never overwritten.

    If ``folder`` already holds results (``particles.csv``, ``fields.h5``, ...), it is renamed to the
    first free ``<folder>.1``, ``<folder>.2``, ... and a fresh folder is made. Returns the new name of
    the earlier results, or None. ``keep_existing`` (a restart) writes into the folder as it is.
    A folder that holds anything but pmpm's results is refused (``output_folder_problem``); the
    partial files of an interrupted run (``checkpoint.h5.tmp``, ...) are removed, and the run says so.
    """
    error = moved = None
    if comm.rank == 0:
        try:
            problem = output_folder_problem(folder)
            if problem is not None:
                raise CaseError(f"output folder {folder}: {problem}")
            for name in LEFTOVER_FILES:
                if (folder / name).is_file():
                    (folder / name).unlink()
                    print(f"pmpm: removed {folder / name}, an incomplete file left by an interrupted run",
                          flush=True)
            if not keep_existing and folder.is_dir() and any((folder / f).exists() for f in RESULT_FILES):
                n = 1
                while folder.with_name(f"{folder.name}.{n}").exists():
                    n += 1
                moved = folder.with_name(f"{folder.name}.{n}")
                folder.rename(moved)
            folder.mkdir(parents=True, exist_ok=True)
        except CaseError as exc:
            error = exc
        except OSError as exc:
            error = CaseError(f"--output {folder}: cannot prepare the output folder: {exc.strerror}")
    agree(comm, error)
    return comm.bcast(moved, root=0)


@dataclass
class SerialOrder:
    """Collective plan to gather owned rows into contiguous slabs of the serial order.

    Rank r ends up holding rows ``[start, stop)`` of the global (serial-order) array.
    """

    comm: object
    n_global: int
    start: int
    stop: int
    send_order: np.ndarray  # owned local rows, grouped by destination rank
    send_counts: np.ndarray
    recv_counts: np.ndarray
    recv_position: np.ndarray  # slab row of each received row

    @classmethod
    def build(cls, comm, serial_index: np.ndarray, n_global: int) -> "SerialOrder":
        size = comm.size
        bounds = np.linspace(0, n_global, size + 1).astype(np.int64)
        dest = np.searchsorted(bounds, serial_index, side="right") - 1
        send_order = np.argsort(dest, kind="stable")
        send_counts = np.bincount(dest, minlength=size).astype(np.int64)
        recv_counts = np.empty(size, np.int64)
        comm.Alltoall(send_counts, recv_counts)
        start, stop = bounds[comm.rank], bounds[comm.rank + 1]
        received = np.empty(recv_counts.sum(), np.int64)
        plan = cls(comm, n_global, start, stop, send_order, send_counts, recv_counts, np.empty(0, np.int64))
        plan._exchange(serial_index.astype(np.int64), received)
        plan.recv_position = received - start
        return plan

    def _exchange(self, values: np.ndarray, out: np.ndarray) -> None:
        row = int(np.prod(values.shape[1:], dtype=int))
        send = np.ascontiguousarray(values[self.send_order])
        s_disp = np.concatenate([[0], np.cumsum(self.send_counts)[:-1]]) * row
        r_disp = np.concatenate([[0], np.cumsum(self.recv_counts)[:-1]]) * row
        from mpi4py import MPI
        mpi_type = MPI._typedict[values.dtype.char]
        self.comm.Alltoallv([send, self.send_counts * row, s_disp, mpi_type],
                            [out, self.recv_counts * row, r_disp, mpi_type])

    def slab(self, values: np.ndarray) -> np.ndarray:
        """Collective. This rank's slab (stop-start, ...) of the serial-order array."""
        received = np.empty((self.recv_counts.sum(),) + values.shape[1:], values.dtype)
        self._exchange(np.ascontiguousarray(values), received)
        out = np.empty((self.stop - self.start,) + values.shape[1:], values.dtype)
        out[self.recv_position] = received
        return out


class FieldWriter:
    """fields.h5 + fields.xdmf: the mesh once, then one group per output time. Collective."""

    def __init__(self, comm, folder: Path, mesh, with_fluid: bool):
        self.comm, self.mesh, self.with_fluid = comm, mesh, with_fluid
        self.path = folder / "fields.h5"
        self.xdmf_path = folder / "fields.xdmf"
        owned = slice(0, mesh.n_owned_cells)
        self.cells = SerialOrder.build(comm, mesh.cell_serial[owned], mesh.n_global_cells)
        owned_vertices = np.flatnonzero(mesh.vertex_owned)
        self.n_global_vertices = int(comm.allreduce(owned_vertices.size))
        self.vertices = SerialOrder.build(comm, mesh.vertex_serial[owned_vertices], self.n_global_vertices)
        self.owned_vertices = owned_vertices
        self.times: list[float] = []
        self.particle_counts: list[int] = []
        with self._open("w-") as f:
            self._write("mesh/vertices", f, self.vertices, mesh.vertex_xyz[owned_vertices])
            connectivity = mesh.vertex_serial[mesh.cell_vertices[owned][:, VTK_ORDER[mesh.cell_type]]]
            self._write("mesh/cells", f, self.cells, connectivity.astype(np.int64))
            self._write("mesh/cell_centers", f, self.cells, mesh.cell_center[owned])
            self._write("mesh/cell_volumes", f, self.cells, mesh.cell_volume[owned])
            f.create_group("output")

    def _open(self, mode):
        if h5py.get_config().mpi:
            return h5py.File(self.path, mode, driver="mpio", comm=self.comm)
        if self.comm.size > 1:
            raise RuntimeError("h5py was loaded without MPI: import pmpm.io before h5py")
        return h5py.File(self.path, mode)

    @staticmethod
    def _write(name, f, plan: SerialOrder, owned_values: np.ndarray):
        slab = plan.slab(owned_values)
        dset = f.create_dataset(name, (plan.n_global,) + owned_values.shape[1:], dtype=owned_values.dtype)
        with dset.collective:
            dset[plan.start:plan.stop] = slab

    def write(self, time: float, fluid_fields: dict, particle_arrays: dict):
        """Collective. Append one output group: cell fields (owned rows) and particle arrays (replicated)."""
        index = len(self.times)
        owned = slice(0, self.mesh.n_owned_cells)
        with self._open("r+") as f:
            group = f.create_group(f"output/{index:06d}")
            group.attrs["time"] = time
            for name, values in fluid_fields.items():
                self._write(f"output/{index:06d}/{name}", f, self.cells, np.ascontiguousarray(values[owned]))
            particles = group.create_group("particles")
            n = 0
            for name, values in particle_arrays.items():
                n = len(values)
                dset = particles.create_dataset(name, values.shape, dtype=values.dtype)
                if self.comm.rank == 0 and n:  # replicated state: one rank writes it
                    dset[...] = values
        self.times.append(time)
        self.particle_counts.append(n)
        if self.comm.rank == 0:
            self.write_xdmf(list(fluid_fields), {k: v.shape[1:] for k, v in particle_arrays.items()})

    def write_xdmf(self, field_names, particle_shapes):
        """The XDMF index over fields.h5 (rank 0): a temporal collection of mesh + particle grids."""
        mesh = self.mesh
        nc, nv = self.mesh.n_global_cells, self.n_global_vertices
        k = mesh.cell_vertices.shape[1]
        h5 = self.path.name
        lines = ['<?xml version="1.0" ?>', '<Xdmf Version="3.0">', "<Domain>",
                 '<Grid Name="fields" GridType="Collection" CollectionType="Temporal">']
        for index, time in enumerate(self.times):
            group = f"/output/{index:06d}"
            lines += [f'<Grid Name="step{index}" GridType="Collection" CollectionType="Spatial">',
                      f'<Time Value="{time:.9g}"/>',
                      f'<Grid Name="mesh" GridType="Uniform">',
                      f'<Topology TopologyType="{XDMF_TOPOLOGY[mesh.cell_type]}" NumberOfElements="{nc}">',
                      f'<DataItem Dimensions="{nc} {k}" NumberType="Int" Precision="8" Format="HDF">{h5}:/mesh/cells</DataItem>',
                      "</Topology>", '<Geometry GeometryType="XYZ">',
                      f'<DataItem Dimensions="{nv} 3" NumberType="Float" Precision="8" Format="HDF">{h5}:/mesh/vertices</DataItem>',
                      "</Geometry>"]
            for name in field_names:
                vector = name == "velocity"
                dims = f"{nc} 3" if vector else f"{nc}"
                lines += [f'<Attribute Name="{name}" AttributeType="{"Vector" if vector else "Scalar"}" Center="Cell">',
                          f'<DataItem Dimensions="{dims}" NumberType="Float" Precision="8" Format="HDF">{h5}:{group}/{name}</DataItem>',
                          "</Attribute>"]
            lines.append("</Grid>")
            n = self.particle_counts[index]
            if n:
                lines += ['<Grid Name="particles" GridType="Uniform">',
                          f'<Topology TopologyType="Polyvertex" NumberOfElements="{n}"/>',
                          '<Geometry GeometryType="XYZ">',
                          f'<DataItem Dimensions="{n} 3" NumberType="Float" Precision="8" Format="HDF">{h5}:{group}/particles/position</DataItem>',
                          "</Geometry>"]
                for name, shape in particle_shapes.items():
                    if name == "position":
                        continue
                    vector = shape == (3,)
                    dims = f"{n} 3" if vector else f"{n}"
                    number = "Int" if name == "id" else "Float"
                    lines += [f'<Attribute Name="{name}" AttributeType="{"Vector" if vector else "Scalar"}" Center="Node">',
                              f'<DataItem Dimensions="{dims}" NumberType="{number}" Precision="8" Format="HDF">{h5}:{group}/particles/{name}</DataItem>',
                              "</Attribute>"]
                lines.append("</Grid>")
            lines.append("</Grid>")
        lines += ["</Grid>", "</Domain>", "</Xdmf>", ""]
        temporary = self.xdmf_path.with_suffix(".xdmf.tmp")
        temporary.write_text("\n".join(lines))
        os.replace(temporary, self.xdmf_path)


class ParticleWriter:
    """particles.csv: one row per particle per output time, ordered by time then id (rank 0 writes)."""

    BASE = ("time", "id", "x", "y", "z", "vx", "vy", "vz", "wx", "wy", "wz", "radius", "density")
    FLUID = ("fx", "fy", "fz", "tx", "ty", "tz")

    def __init__(self, comm, folder: Path, with_fluid: bool, extra: tuple[str, ...] = ()):
        self.comm = comm
        self.columns = self.BASE + (self.FLUID if with_fluid else ()) + tuple(extra)
        self.path = folder / "particles.csv"
        if comm.rank == 0:
            with open(self.path, "x") as f:
                f.write(",".join(self.columns) + "\n")

    def write(self, time: float, state, hydro_force=None, hydro_torque=None, extra: dict | None = None):
        """Collective. Append the rows of one output time (``state``: every particle, the same on
        every rank): each rank formats a share of the rows (the formatting, not the file, is the
        cost), rank 0 writes them in order."""
        n = len(state.id)
        share = slice(n * self.comm.rank // self.comm.size, n * (self.comm.rank + 1) // self.comm.size)
        blocks = [np.full((n, 1), time), state.id[:, None].astype(float), state.x, state.v,
                  state.omega, state.radius[:, None], state.density[:, None]]
        if "fx" in self.columns:
            blocks += [hydro_force, hydro_torque]
        for name in self.columns[len(self.BASE) + (6 if "fx" in self.columns else 0):]:
            blocks.append(np.asarray(extra[name], float)[:, None])
        table = np.hstack([block[share] for block in blocks]) if n else np.zeros((0, len(self.columns)))
        row = ",".join(["%.9g", "%d"] + ["%.12g"] * (len(self.columns) - 2)) + "\n"
        text = "".join([row % tuple(values) for values in table.tolist()])
        texts = self.comm.gather(text, root=0) if self.comm.size > 1 else [text]
        if self.comm.rank == 0 and n:
            with open(self.path, "a") as f:
                f.writelines(texts)


class BodyWriter:
    """bodies.csv: the fluid's force and torque on each [[body]], one row per body per output time
    (rank 0 writes; the forces are the same on every rank)."""

    COLUMNS = ("time", "body", "fx", "fy", "fz", "tx", "ty", "tz")

    def __init__(self, comm, folder: Path, names: tuple[str, ...]):
        self.comm, self.names, self.path = comm, names, folder / "bodies.csv"
        if comm.rank == 0:
            with open(self.path, "x") as f:
                f.write(",".join(self.COLUMNS) + "\n")

    def write(self, time: float, forces) -> None:
        if self.comm.rank != 0 or forces is None:
            return
        with open(self.path, "a") as f:
            for name, row in zip(self.names, forces):
                f.write(f"{time:.9g},{name}," + ",".join(f"{value:.12g}" for value in row) + "\n")


@dataclass
class Writers:
    """The files of one output time: particles.csv rows, a fields.h5 group, bodies.csv rows.
    Collective."""

    particles: ParticleWriter
    fields: FieldWriter
    with_fluid: bool
    bodies: BodyWriter | None = None

    @classmethod
    def open(cls, comm, folder: Path, mesh, with_fluid: bool, body_names: tuple[str, ...] = ()) -> "Writers":
        bodies = BodyWriter(comm, folder, body_names) if with_fluid and body_names else None
        return cls(ParticleWriter(comm, folder, with_fluid), FieldWriter(comm, folder, mesh, with_fluid), with_fluid,
                   bodies)

    def write(self, state) -> None:
        """Collective. One output time of a ``pmpm.state.RunState`` (particles owned by ranks gathered first)."""
        particles, force, torque = state.particles, state.hydro_force, state.hydro_torque
        if state.partition is not None:
            particles, force, torque = gather_with(self.fields.comm, particles, force, torque)
        fields = {}
        if self.with_fluid:
            fields = {"velocity": state.fluid.u, "pressure": state.fluid.p, "volume_fraction": state.volume_fraction}
        self.particles.write(state.time, particles, force, torque)
        arrays = {"id": particles.id, "position": particles.x, "velocity": particles.v,
                  "angular_velocity": particles.omega, "radius": particles.radius, "density": particles.density}
        self.fields.write(state.time, fields, arrays)
        if self.bodies is not None:
            self.bodies.write(state.time, state.body_forces)


def write_summary(comm, folder: Path, summary: dict) -> None:
    """summary.json, written by rank 0 at the end of the run."""
    if comm.rank == 0:
        temporary = folder / "summary.json.tmp"
        temporary.write_text(json.dumps(summary, indent=2, default=_json_default) + "\n")
        os.replace(temporary, folder / "summary.json")


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(type(value))
