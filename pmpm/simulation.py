"""The time loop: builds the pieces a case asks for and runs them, timing each stage.

One step, top to bottom (ARCHITECTURE.md): inject → locate → flow → patch → reduce drag/torque →
forces → move with collisions → owners/outflow → write. A section absent from the case builds
nothing, and its stages cost nothing.
"""
from __future__ import annotations

import math
import time as wallclock
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import io
from .case import Case, case_path, load_case, suggest
from .errors import CaseError, NumericalError
from .collisions import (advance_with_collisions, build_walls, check_initial_particles, collision_settings,
                         overlaps_existing)
from .forces import field_forces_of_case, gravity_buoyancy
from .injection import NewParticles, build_injectors, initial_particles
from .mesh import Mesh
from .parallel import agree, allreduce_sum, print0
from .particles import ParticleState, accelerate


def build_mesh(comm, case: Case) -> Mesh:
    """Collective. The case's mesh, distributed over ``comm``."""
    if case.box is not None:
        return Mesh.from_box(comm, case.box.lower, case.box.upper, case.box.cells, case.mesh.cell_type)
    return Mesh.from_file(comm, case.resolve(case.mesh.file))


def check_boundaries(case: Case, mesh: Mesh) -> None:
    """Every [boundary.<name>] and deposition zone must name a boundary of the mesh."""
    names = list(mesh.boundary_names)
    listed = [(f"[boundary.{n}]", n) for n in case.boundaries]
    listed += [("[deposition] zones", n) for n in (case.deposition.zones if case.deposition else ())]
    for where, name in listed:
        if name not in names:
            raise CaseError(f"{case.path.name}: {where}: the mesh has no boundary \"{name}\"{suggest(name, names)}"
                            f" (it has: {', '.join(names)})")


@dataclass
class StageTimes:
    """Wall seconds per stage, summed over the run (rank 0's clock)."""

    seconds: dict = field(default_factory=dict)

    def add(self, stage: str, seconds: float):
        self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds


class Timer:
    """``with Timer(times, "flow"):`` adds the block's wall time to a stage."""

    def __init__(self, times: StageTimes, stage: str):
        self.times, self.stage = times, stage

    def __enter__(self):
        self.start = wallclock.perf_counter()

    def __exit__(self, *exc):
        self.times.add(self.stage, wallclock.perf_counter() - self.start)


class Progress:
    """Compact progress lines on rank 0: step, simulated time, wall time, ETA."""

    def __init__(self, comm, end_time: float, quiet: bool, every_seconds: float = 5.0):
        self.comm, self.end_time, self.quiet, self.every = comm, end_time, quiet, every_seconds
        self.start = self.last = wallclock.perf_counter()

    def update(self, step: int, time: float, extra: str = "", force: bool = False):
        now = wallclock.perf_counter()
        if self.quiet or (not force and now - self.last < self.every):
            return
        self.last = now
        elapsed = now - self.start
        eta = elapsed * (self.end_time - time) / time if time > 0 else math.nan
        print0(self.comm, f"step {step:7d}  t = {time:.6g} s  ({100 * time / self.end_time:5.1f} %)  "
                          f"wall {elapsed:8.1f} s  ETA {eta:8.1f} s{extra}")


def run_from_arguments(comm, arguments) -> None:
    """Collective. Everything ``python -m pmpm`` does after parsing the command line."""
    case = load_case(case_path(arguments.case), arguments.set)
    output = Path(arguments.output) if arguments.output else case.folder / "output"
    if arguments.restart:
        raise CaseError("--restart: restarting from a checkpoint is not available yet in this version")
    start = wallclock.perf_counter()
    mesh = build_mesh(comm, case)
    check_boundaries(case, mesh)
    simulation = Simulation(comm, case, mesh, quiet=arguments.quiet)
    setup_seconds = wallclock.perf_counter() - start
    print0(comm, simulation.describe(setup_seconds))
    if arguments.check:
        return
    moved = io.prepare_output_folder(comm, output.resolve())
    if moved is not None:
        print0(comm, f"pmpm: the earlier results in {output} were kept as {moved}")
    simulation.run(output.resolve(), setup_seconds)


class Simulation:
    """The pieces a case asks for, and the time loop over them. Collective."""

    def __init__(self, comm, case: Case, mesh: Mesh, quiet: bool = False):
        self.comm, self.case, self.mesh, self.quiet = comm, case, mesh, quiet
        self.times = StageTimes()
        self.time, self.step = 0.0, 0
        self.removed = 0  # particles that left the domain
        self.particles = ParticleState.empty()
        self.injectors = build_injectors(case)
        self.walls = build_walls(case, mesh) if (case.collisions or case.field_forces or case.deposition) else None
        self.settings = collision_settings(case) if case.collisions else None
        self.flow = self.fluid_state = None
        if case.fluid is not None:
            raise CaseError(f"{case.path.name}: [fluid]: the flow solver is not part of this build yet")
        start = initial_particles(case)
        self.add_particles(start, validate=True)

    # -- particles ------------------------------------------------------------------------------
    def add_particles(self, new, validate: bool = False) -> None:
        """Collective. Append particles (identically on every rank), checked against the domain."""
        if len(new) == 0:
            return
        inside = self.inside_domain(new.x)
        if validate:
            check_initial_particles(self.case, new, inside, self.walls)
        keep = inside
        if not validate:  # injected: skip releases outside the domain or onto other particles
            keep &= ~overlaps_existing(self.particles, new)
        ids = self.next_id() + np.arange(int(keep.sum()))
        self.particles.append(ids, new.x[keep], new.v[keep], new.omega[keep], new.radius[keep],
                              new.density[keep], new.motion[keep])

    def next_id(self) -> int:
        return int(self.particles.id.max()) + 1 if len(self.particles.id) else self._first_free_id

    _first_free_id = 0

    def inside_domain(self, points: np.ndarray) -> np.ndarray:
        """Collective. True where a point lies in some rank's owned cells."""
        found = (self.mesh.find_owned_cells(points) >= 0).astype(np.int64)
        return allreduce_sum(self.comm, found) > 0

    # -- the loop -------------------------------------------------------------------------------
    def run(self, output: Path, setup_seconds: float) -> None:
        """Collective. Run to end_time (or the wall-time limit), writing outputs on the way."""
        run = self.case.run
        with_fluid = self.flow is not None
        self.particle_writer = io.ParticleWriter(self.comm, output, with_fluid)
        self.field_writer = io.FieldWriter(self.comm, output, self.mesh, with_fluid)
        progress = Progress(self.comm, run.end_time, self.quiet)
        started = wallclock.perf_counter()
        self.write_outputs()
        next_output = run.output_every
        status = "completed"
        try:
            while self.time < run.end_time * (1 - 1e-12):
                dt = min(run.dt, run.end_time - self.time)
                self.advance(dt)
                if self.time >= next_output * (1 - 1e-9) or self.time >= run.end_time * (1 - 1e-12):
                    with Timer(self.times, "output"):
                        self.write_outputs()
                    while next_output <= self.time * (1 + 1e-9):
                        next_output += run.output_every
                progress.update(self.step, self.time, f"  particles {len(self.particles.id)}")
                if run.wall_time_limit and wallclock.perf_counter() - started > run.wall_time_limit:
                    status = "stopped at the wall-time limit"
                    self.write_outputs()
                    break
        except NumericalError:
            status = "numerical failure"
            raise
        finally:
            total = wallclock.perf_counter() - started
            progress.update(self.step, self.time, force=True)
            io.write_summary(self.comm, output, self.summary(status, setup_seconds, total))

    def advance(self, dt: float) -> None:
        """Collective. One time step, stage by stage."""
        case, state = self.case, self.particles
        # 1. inject new particles
        if self.injectors:
            with Timer(self.times, "injection"):
                new = [injector.due(self.time + dt) for injector in self.injectors]
                self.add_particles(NewParticles.concatenate(new))
        # 6. gravity with buoyancy and field forces
        with Timer(self.times, "forces"):
            force = gravity_buoyancy(state, np.array(case.run.gravity), 0.0)
            if case.field_forces is not None:
                force += field_forces_of_case(state, self.walls, case.field_forces)
        # 7. update V and ω, then move with collisions resolved in time order
        with Timer(self.times, "collisions" if self.settings else "motion"):
            accelerate(state, force, np.zeros_like(force), dt)
            if self.settings is not None:
                self.collision_stats = advance_with_collisions(state, self.walls, dt, self.settings)
            else:
                free = state.motion != 1
                state.x[free] += state.v[free] * dt
        # 8. particles that left the domain are removed
        with Timer(self.times, "owners"):
            outside = ~self.inside_domain(state.x)
            if outside.any():
                self.removed += int(outside.sum())
                state.remove(outside)
        self.time += dt
        self.step += 1
        check_finite(state, self.step, self.time)

    def write_outputs(self) -> None:
        """Collective. One output time: particles.csv rows and a fields.h5 group."""
        state = self.particles
        self.particle_writer.write(self.time, state)
        arrays = {"id": state.id, "position": state.x, "velocity": state.v, "angular_velocity": state.omega,
                  "radius": state.radius, "density": state.density}
        self.field_writer.write(self.time, {}, arrays)

    # -- reporting ------------------------------------------------------------------------------
    def describe(self, setup_seconds: float) -> str:
        case, mesh = self.case, self.mesh
        run = case.run
        steps = math.ceil(run.end_time / run.dt - 1e-9)
        return "\n".join([
            f"pmpm: case {case.path}",
            f"  models:    {', '.join(case.models()) or 'none'}",
            f"  mesh:      {mesh.describe()}",
            f"  particles: {len(self.particles.id)} at start, {len(self.injectors)} injection(s)",
            f"  ranks:     {self.comm.size}",
            f"  time:      0 → {run.end_time:g} s, dt = {run.dt:g} s ({steps} steps), output every {run.output_every:g} s",
            f"  setup:     {setup_seconds:.2f} s",
        ])

    def summary(self, status: str, setup_seconds: float, total_seconds: float) -> dict:
        state = self.particles
        kinetic = 0.5 * float(np.sum(state.mass * np.sum(state.v ** 2, axis=1)))
        return {
            "case": str(self.case.path), "status": status, "ranks": self.comm.size,
            "cells": self.mesh.n_global_cells, "particles": len(state.id), "particles_removed": self.removed,
            "steps": self.step, "simulated_time": self.time, "models": self.case.models(),
            "wall_seconds": {"total": total_seconds, "setup": setup_seconds, **self.times.seconds},
            "diagnostics": {"particle_kinetic_energy": kinetic,
                            "particle_momentum": (state.mass[:, None] * state.v).sum(axis=0)},
        }


def check_finite(state, step: int, time: float) -> None:
    """Raise NumericalError naming the first particle whose state is not finite."""
    bad = ~np.isfinite(state.x).all(axis=1) | ~np.isfinite(state.v).all(axis=1)
    if bad.any():
        pid = int(state.id[np.argmax(bad)])
        raise NumericalError(f"step {step}, t = {time:.6g} s: particle {pid} has a non-finite position or "
                             "velocity; reduce [run] dt")
