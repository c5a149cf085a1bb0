"""checkpoint.h5: the whole run state, written collectively and replaced atomically.

Written to ``checkpoint.h5.tmp`` and renamed over ``checkpoint.h5`` only when complete, so a run
killed at any moment leaves the previous checkpoint whole. Everything is stored in an order
independent of the rank count, so a run may restart on another number of ranks:

- attributes: time, step, next particle id, particles removed (and through which boundary), pressure
  iterations, n_global_cells,
  each injection's next release;
- ``particles/*``: the particle arrays (gathered where ranks own particles), in id order, and their
  last hydrodynamic force and torque; ``ownership/partition``: the ranks' boxes, where they own
  particles (a restart on as many ranks takes them again);
- ``coupling/*``, ``contacts/*``: the coupling's and the contact solver's memory, where the run has one;
- ``walls/*``: the wall triangles as they are now (rigid walls move); ``collisions``: the run's counts;
- ``fluid/velocity``, ``fluid/pressure``, ``fluid/volume_fraction``: cells in the serial order of
  the undistributed mesh;
- ``fluid/face_key`` (the 3 smallest serial vertex numbers of a face), ``fluid/face_from`` (the
  serial cell the flux leaves), ``fluid/face_flux``: every rank's faces, in any order, a face
  between two ranks once from each side; ``fluid/face_canonical`` marks one copy of each face.
"""
from __future__ import annotations

import json
import os
from dataclasses import fields, replace
from pathlib import Path

import numpy as np

from .collisions import ContactMemory
from .coupling import CouplingMemory
from .errors import CaseError
from .fluid import FluidState
from .io import SerialOrder, h5py
from .mesh import match_rows
from .ownership import Partition, bisect, gather_with
from .parallel import agree, exscan_offset
from .particles import ParticleState

PARTICLE_FIELDS = tuple(f.name for f in fields(ParticleState))
WALL_FIELDS = ("a", "b", "c", "normal", "center")   # what moves of a wall triangle


def face_identity(mesh):
    """Each local face's key (its 3 smallest serial vertex numbers, (n_faces, 3)) and the serial
    number of the cell its flux leaves (n_faces,); and which faces this rank writes as the one
    copy of a face that two ranks hold (the copy of the rank with the lower global cell number)."""
    owner, neighbour = mesh.face_cells[:, 0], mesh.face_cells[:, 1]
    gid = mesh.cell_gid
    canonical = (neighbour < 0) | (gid[owner] < np.where(neighbour >= 0, gid[np.maximum(neighbour, 0)], -1))
    keys = np.sort(mesh.vertex_serial[mesh.face_vertices], axis=1)[:, :3]
    return keys, mesh.cell_serial[owner], canonical


def write(comm, folder: Path, mesh, state) -> None:
    """Collective. Write the run state (``pmpm.state.RunState``) to ``folder/checkpoint.h5`` atomically."""
    temporary, final = folder / "checkpoint.h5.tmp", folder / "checkpoint.h5"
    with h5py.File(temporary, "w", driver="mpio", comm=comm) as f:
        f.attrs.update(time=state.time, step=state.step, dt=state.dt, next_id=state.next_id, removed=state.removed,
                       pressure_iterations=state.pressure_iterations, n_global_cells=mesh.n_global_cells,
                       injector_releases=np.array(state.releases, np.int64),
                       collisions=json.dumps(state.collision_totals), fresh_from=state.fresh_from,
                       injection_counts=json.dumps(state.injection_counts),
                       removed_through=json.dumps(state.removed_through))
        particles, hydro_force, hydro_torque, contacts = state.particles, state.hydro_force, state.hydro_torque, \
            state.contacts
        coupling = state.coupling
        if state.partition is not None:   # owned by ranks: gathered, in id order
            particles, hydro_force, hydro_torque = gather_with(comm, particles, hydro_force, hydro_torque)
            contacts = gathered_memory(comm, contacts) if contacts is not None else None
            coupling = coupling.gathered(comm) if coupling is not None else None
        groups = {"particles": {**{name: getattr(particles, name) for name in PARTICLE_FIELDS},
                                "hydro_force": hydro_force, "hydro_torque": hydro_torque}}
        if state.partition is not None:
            groups["ownership"] = {"partition": state.partition.to_array()}
        if coupling is not None:
            groups["coupling"] = coupling.to_arrays()
        if contacts is not None:
            groups["contacts"] = contacts.to_arrays()
        if state.body_forces is not None:
            groups["bodies"] = {"forces": state.body_forces}
        if state.walls is not None:
            groups["walls"] = {name: getattr(state.walls, name) for name in WALL_FIELDS}
        for group, arrays in groups.items():   # replicated on every rank: rank 0 writes them
            for name, values in arrays.items():
                values = np.asarray(values)
                dset = f.create_dataset(f"{group}/{name}", values.shape, dtype=values.dtype)
                if comm.rank == 0 and values.size:
                    dset[...] = values
        if state.fluid is not None:
            write_fluid(comm, f, mesh, state)
    comm.Barrier()
    if comm.rank == 0:
        os.replace(temporary, final)
    comm.Barrier()


def write_fluid(comm, f, mesh, state) -> None:
    """Collective. The cell fields in serial order, and each face's flux once."""
    owned = slice(0, mesh.n_owned_cells)
    cells = SerialOrder.build(comm, mesh.cell_serial[owned], mesh.n_global_cells)
    for name, values in (("velocity", state.fluid.u[owned]), ("pressure", state.fluid.p[owned]),
                         ("volume_fraction", state.volume_fraction[owned])):
        slab = cells.slab(np.ascontiguousarray(values))
        dset = f.create_dataset(f"fluid/{name}", (mesh.n_global_cells,) + values.shape[1:], dtype=float)
        with dset.collective:
            dset[cells.start:cells.stop] = slab
    # every rank's faces, a face between two ranks once from each: the fluxes the two ranks hold
    # differ by round-off, and a restart on the same ranks continues bit for bit with each its own
    keys, from_cell, canonical = face_identity(mesh)
    count = len(keys)
    start = exscan_offset(comm, count)
    total = comm.allreduce(count)
    for name, values in (("face_key", keys), ("face_from", from_cell), ("face_canonical", canonical),
                         ("face_flux", state.fluid.flux)):
        dset = f.create_dataset(f"fluid/{name}", (total,) + values.shape[1:], dtype=values.dtype)
        with dset.collective:
            dset[start:start + count] = values


def read(comm, path: Path) -> dict:
    """Collective. The whole checkpoint as arrays on every rank (checked: a pmpm checkpoint)."""
    error, data = None, None
    try:
        with h5py.File(path, "r") as f:
            data = {"attrs": dict(f.attrs)}
            for group in ("particles", "coupling", "contacts", "walls", "bodies", "fluid", "ownership"):
                if group in f:
                    data[group] = {k: f[f"{group}/{k}"][...] for k in f[group]}
            if "particles" not in data:
                raise KeyError("no particles group")
    except FileNotFoundError:
        error = CaseError(f"--restart {path}: no such checkpoint file")
    except (OSError, KeyError) as exc:
        error = CaseError(f"--restart {path}: not a pmpm checkpoint ({exc})")
    agree(comm, error)
    return data


def gathered_memory(comm, memory: ContactMemory) -> ContactMemory:
    """Collective. Every rank's contact memory, in key order."""
    parts = comm.allgather(memory.to_arrays())
    joined = ContactMemory.from_arrays({name: np.concatenate([part[name] for part in parts]) for name in parts[0]})
    order = np.argsort(joined.keys, kind="stable")
    return ContactMemory.from_arrays({name: values[order] for name, values in joined.to_arrays().items()})


def restore(comm, data: dict, model, initial, path: Path):
    """Collective. The run state of a checkpoint, for ``model`` (built from the same case), whose
    initial state ``initial`` gives what the checkpoint leaves out (a case's unmoving walls). Where
    ranks own particles (``initial.partition``), each rank keeps its own, in the boxes the checkpoint
    was written with if it was written on as many ranks (the same trajectory continues)."""
    attrs, mesh = data["attrs"], model.mesh
    if int(attrs["n_global_cells"]) != mesh.n_global_cells:
        raise CaseError(f"--restart {path}: the checkpoint is of a mesh of {int(attrs['n_global_cells'])} cells, "
                        f"this case's mesh has {mesh.n_global_cells}")
    if ("fluid" in data) != (initial.fluid is not None):
        raise CaseError(f"--restart {path}: the checkpoint {'has' if 'fluid' in data else 'has no'} flow, "
                        f"this case {'has' if initial.fluid is not None else 'has no'} [fluid]")
    releases = np.atleast_1d(attrs["injector_releases"])
    if len(releases) != len(model.injectors):
        raise CaseError(f"--restart {path}: the checkpoint has {len(releases)} injection(s), this case "
                        f"{len(model.injectors)}")
    stored = data["particles"]
    template = ParticleState.empty()
    particles = ParticleState(**{name: stored[name].astype(getattr(template, name).dtype)
                                 .reshape((-1,) + getattr(template, name).shape[1:]) for name in PARTICLE_FIELDS})
    state = replace(initial, time=float(attrs["time"]), step=int(attrs["step"]), dt=float(attrs.get("dt", 0.0)),
                    next_id=int(attrs["next_id"]),
                    removed=int(attrs["removed"]), releases=tuple(int(k) for k in releases),
                    pressure_iterations=int(attrs.get("pressure_iterations", 0)),
                    collision_totals=json.loads(attrs.get("collisions", "{}")), particles=particles,
                    fresh_from=int(attrs.get("fresh_from", attrs["next_id"])),
                    injection_counts=json.loads(attrs.get("injection_counts", "{}")),
                    removed_through=json.loads(attrs.get("removed_through", "{}")),
                    hydro_force=stored["hydro_force"].reshape(-1, 3), hydro_torque=stored["hydro_torque"].reshape(-1, 3),
                    contacts=ContactMemory.from_arrays(data["contacts"]) if "contacts" in data else None,
                    body_forces=data["bodies"]["forces"].reshape(-1, 6) if "bodies" in data else None)
    if "coupling" in data and initial.coupling is not None:
        state = replace(state, coupling=CouplingMemory.from_arrays(data["coupling"]))
    if "walls" in data and initial.walls is not None and len(data["walls"]["a"]) == len(initial.walls):
        state = replace(state, walls=replace(initial.walls, **{name: data["walls"][name].reshape(-1, 3)
                                                               for name in WALL_FIELDS}))
    if "fluid" in data:
        state = replace(state, **restored_fluid(comm, data["fluid"], mesh, path))
    if initial.partition is not None:   # ranks own particles: the boxes written, on as many ranks
        stored = Partition.from_array(data["ownership"]["partition"]) if "ownership" in data else None
        if model.flow is not None:   # (in a flow, the mesh's)
            stored = initial.partition
        elif stored is None or len(stored.lower) != comm.size:
            x = state.particles.x if comm.rank == 0 else np.zeros((0, 3))
            stored = bisect(comm, x, (mesh.lower, mesh.upper))
        state = state.owned_by(comm.rank, stored)
    return state


def restored_fluid(comm, stored: dict, mesh, path: Path) -> dict:
    """Collective. The flow and the volume fraction of a checkpoint on this rank's cells. A face
    takes the flux stored with its own orientation (this rank's copy, on the same ranks), else the
    one copy of it, turned where it was stored from the other side."""
    keys, from_cell, _ = face_identity(mesh)
    flux = np.zeros(len(keys))
    same = match_rows(np.column_stack([keys, from_cell]), np.column_stack([stored["face_key"], stored["face_from"]]))
    flux[same >= 0] = stored["face_flux"][same[same >= 0]]
    rest = np.flatnonzero(same < 0)
    canonical = np.flatnonzero(stored["face_canonical"])
    where = match_rows(keys[rest], stored["face_key"][canonical])
    agree(comm, CaseError(f"--restart {path}: the checkpoint's faces do not match this case's mesh")
          if (where < 0).any() else None)
    where = canonical[where]
    flux[rest] = np.where(stored["face_from"][where] == from_cell[rest], 1.0, -1.0) * stored["face_flux"][where]
    fluid = FluidState(stored["velocity"][mesh.cell_serial].reshape(-1, 3), stored["pressure"][mesh.cell_serial], flux)
    return {"fluid": fluid, "volume_fraction": stored["volume_fraction"][mesh.cell_serial]}
