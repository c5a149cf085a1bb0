"""checkpoint.h5: the whole state of a run, written collectively and replaced atomically.

Written to ``checkpoint.h5.tmp`` and renamed over ``checkpoint.h5`` only when complete, so a run
killed at any moment leaves the previous checkpoint whole (SPEC §4). Everything is stored in an
order independent of the rank count, so a run may restart on another number of ranks:

- attributes: time, step, next particle id, particles removed, n_global_cells, injector releases;
- ``particles/*``: the replicated particle arrays (and their last hydrodynamic force and torque,
  and the coupling's fluid momentum under each particle at the end of the last step);
- ``fluid/velocity``, ``fluid/pressure``: cells in the serial order of the undistributed mesh;
- ``fluid/face_key`` (the 3 smallest serial vertex numbers of a face), ``fluid/face_from`` (the
  serial cell the flux leaves) and ``fluid/face_flux``: each face once, in any order.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .errors import CaseError
from .io import SerialOrder, h5py
from .mesh import match_rows
from .parallel import agree, exscan_offset

PARTICLE_FIELDS = ("id", "x", "v", "omega", "radius", "density", "motion", "deposited")


def face_identity(mesh):
    """The faces this rank writes (each face once over all ranks), their keys and 'from' cells."""
    owner, neighbour = mesh.face_cells[:, 0], mesh.face_cells[:, 1]
    gid = mesh.cell_gid
    mine = (neighbour < 0) | (gid[owner] < np.where(neighbour >= 0, gid[np.maximum(neighbour, 0)], -1))
    keys = np.sort(mesh.vertex_serial[mesh.face_vertices], axis=1)[:, :3]
    return mine, keys, mesh.cell_serial[owner]


def write(comm, folder: Path, mesh, simulation) -> None:
    """Collective. Write the simulation's state to ``folder/checkpoint.h5`` atomically."""
    temporary, final = folder / "checkpoint.h5.tmp", folder / "checkpoint.h5"
    state = simulation.particles
    with h5py.File(temporary, "w", driver="mpio", comm=comm) as f:
        f.attrs.update(time=simulation.time, step=simulation.step, next_id=simulation.next_id(),
                       removed=simulation.removed, n_global_cells=mesh.n_global_cells,
                       injector_releases=np.array([i.next_release for i in simulation.injectors], np.int64))
        group = f.create_group("particles")
        arrays = {name: getattr(state, name) for name in PARTICLE_FIELDS}
        arrays.update(hydro_force=simulation.hydro_force, hydro_torque=simulation.hydro_torque)
        coupling = getattr(simulation, "coupling", None)
        if coupling is not None and coupling.internal_end is not None:
            # the penalty's fluid momentum under each particle at the end of the last step (by id)
            ids, fluid_under, centres = coupling.internal_end
            arrays.update(coupling_ids=ids, coupling_fluid_under=fluid_under, coupling_centres=centres)
        for name, values in arrays.items():
            values = np.asarray(values)
            dset = group.create_dataset(name, values.shape, dtype=values.dtype)
            if comm.rank == 0 and values.size:
                dset[...] = values
        if simulation.fluid_state is not None:
            fluid = simulation.fluid_state
            owned = slice(0, mesh.n_owned_cells)
            cells = SerialOrder.build(comm, mesh.cell_serial[owned], mesh.n_global_cells)
            for name, values in (("velocity", fluid.u[owned]), ("pressure", fluid.p[owned])):
                slab = cells.slab(np.ascontiguousarray(values))
                dset = f.create_dataset(f"fluid/{name}", (mesh.n_global_cells,) + values.shape[1:], dtype=float)
                with dset.collective:
                    dset[cells.start:cells.stop] = slab
            mine, keys, from_cell = face_identity(mesh)
            count = int(mine.sum())
            start = exscan_offset(comm, count)
            total = comm.allreduce(count)
            for name, values in (("face_key", keys[mine]), ("face_from", from_cell[mine]),
                                 ("face_flux", fluid.flux[mine])):
                dset = f.create_dataset(f"fluid/{name}", (total,) + values.shape[1:], dtype=values.dtype)
                with dset.collective:
                    dset[start:start + count] = values
    comm.Barrier()
    if comm.rank == 0:
        os.replace(temporary, final)
    comm.Barrier()


def read(comm, path: Path) -> dict:
    """Collective. The whole checkpoint as arrays on every rank (checked: a pmpm checkpoint)."""
    error, data = None, None
    try:
        with h5py.File(path, "r") as f:
            data = {"attrs": dict(f.attrs), "particles": {k: f[f"particles/{k}"][...] for k in f["particles"]}}
            if "fluid" in f:
                data["fluid"] = {k: f[f"fluid/{k}"][...] for k in f["fluid"]}
    except FileNotFoundError:
        error = CaseError(f"--restart {path}: no such checkpoint file")
    except (OSError, KeyError) as exc:
        error = CaseError(f"--restart {path}: not a pmpm checkpoint ({exc})")
    agree(comm, error)
    return data


def restore(comm, data: dict, mesh, simulation, path: Path) -> None:
    """Collective. Put a checkpoint's state into a freshly built simulation of the same case."""
    attrs = data["attrs"]
    if int(attrs["n_global_cells"]) != mesh.n_global_cells:
        raise CaseError(f"--restart {path}: the checkpoint is of a mesh of {int(attrs['n_global_cells'])} cells, "
                        f"this case's mesh has {mesh.n_global_cells}")
    if ("fluid" in data) != (simulation.fluid_state is not None):
        raise CaseError(f"--restart {path}: the checkpoint {'has' if 'fluid' in data else 'has no'} flow, "
                        f"this case {'has' if simulation.fluid_state is not None else 'has no'} [fluid]")
    releases = np.atleast_1d(attrs["injector_releases"])
    if len(releases) != len(simulation.injectors):
        raise CaseError(f"--restart {path}: the checkpoint has {len(releases)} injection(s), this case "
                        f"{len(simulation.injectors)}")
    simulation.time, simulation.step = float(attrs["time"]), int(attrs["step"])
    simulation.removed = int(attrs["removed"])
    simulation._first_free_id = int(attrs["next_id"])
    if simulation.fluid_state is not None:  # the flow has carried every particle of the checkpoint
        simulation.flow_knows_id = simulation._first_free_id - 1
    for injector, k in zip(simulation.injectors, releases):
        injector.next_release = int(k)
    particles = data["particles"]
    state = simulation.particles
    for name in PARTICLE_FIELDS:
        setattr(state, name, particles[name].astype(getattr(state, name).dtype).reshape((-1,) + getattr(state, name).shape[1:]))
    simulation.hydro_force = particles["hydro_force"].reshape(-1, 3)
    simulation.hydro_torque = particles["hydro_torque"].reshape(-1, 3)
    if "coupling_ids" in particles and simulation.coupling is not None:
        simulation.coupling.internal_end = (particles["coupling_ids"].astype(np.int64),
                                            particles["coupling_fluid_under"].reshape(-1, 6),
                                            particles["coupling_centres"].reshape(-1, 3))
    if simulation.fluid_state is not None:
        fluid, stored = simulation.fluid_state, data["fluid"]
        fluid.u[:] = stored["velocity"][mesh.cell_serial]
        fluid.p[:] = stored["pressure"][mesh.cell_serial]
        _, keys, from_cell = face_identity(mesh)
        where = match_rows(keys, stored["face_key"])
        agree(comm, CaseError(f"--restart {path}: the checkpoint's faces do not match this case's mesh")
              if (where < 0).any() else None)
        sign = np.where(stored["face_from"][where] == from_cell, 1.0, -1.0)
        fluid.flux[:] = sign * stored["face_flux"][where]
