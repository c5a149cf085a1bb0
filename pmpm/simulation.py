"""The time loop: builds the pieces a case asks for and runs them, timing each stage.

One step, top to bottom (ARCHITECTURE.md): inject → locate → flow → patch → reduce drag/torque →
forces → move with collisions → owners/outflow → write. A section absent from the case builds
nothing, and its stages cost nothing.
"""
from __future__ import annotations

import copy
import math
import time as wallclock
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mpi4py import MPI

from . import checkpoint, io
from .case import Case, case_path, load_case, suggest
from .errors import CaseError, NumericalError
from .collisions import (advance_with_collisions, build_walls, check_initial_particles, collision_settings,
                         overlaps_existing)
from .coupling import Coupling
from .fluid import FlowSolver
from .forces import field_forces_of_case, gravity_buoyancy
from .injection import NewParticles, build_injectors, initial_particles
from .mesh import Mesh
from .parallel import agree, allreduce_sum, print0, warn
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

    def __init__(self, comm, end_time: float, quiet: bool, every_seconds: float = 5.0, start_time: float = 0.0):
        self.comm, self.end_time, self.quiet, self.every = comm, end_time, quiet, every_seconds
        self.start_time = start_time
        self.start = self.last = wallclock.perf_counter()

    def update(self, step: int, time: float, extra: str = "", force: bool = False):
        now = wallclock.perf_counter()
        if self.quiet or (not force and now - self.last < self.every):
            return
        self.last = now
        elapsed = now - self.start
        done = time - self.start_time
        eta = elapsed * (self.end_time - time) / done if done > 0 else math.nan
        print0(self.comm, f"step {step:7d}  t = {time:.6g} s  ({100 * time / self.end_time:5.1f} %)  "
                          f"wall {elapsed:8.1f} s  ETA {eta:8.1f} s{extra}")


def run_from_arguments(comm, arguments) -> None:
    """Collective. Everything ``python -m pmpm`` does after parsing the command line."""
    case = load_case(case_path(arguments.case), arguments.set)
    output = Path(arguments.output) if arguments.output else case.folder / "output"
    restart = checkpoint.read(comm, Path(arguments.restart)) if arguments.restart else None
    start = wallclock.perf_counter()
    mesh = build_mesh(comm, case)
    check_boundaries(case, mesh)
    simulation = Simulation(comm, case, mesh, quiet=arguments.quiet)
    if restart is not None:
        checkpoint.restore(comm, restart, mesh, simulation, Path(arguments.restart))
        print0(comm, f"pmpm: restarting from {arguments.restart} at t = {simulation.time:g} s, step {simulation.step}")
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
        self.collision_totals = {}  # summed collision statistics (pmpm.collisions.advance_with_collisions)
        self.particles = ParticleState.empty()
        self.injectors = build_injectors(case)
        self.walls = build_walls(case, mesh) if (case.collisions or case.field_forces or case.deposition) else None
        self.settings = collision_settings(case) if case.collisions else None
        self.flow = self.fluid_state = self.coupling = None
        self.fluid_density = 0.0
        if case.fluid is not None:
            self.fluid_density = case.fluid.density
            self.flow = FlowSolver(mesh, case.fluid, case.boundaries)
            self.fluid_state = self.flow.initial_state()
            self.coupling = Coupling(mesh, case.coupling, case.fluid.density, case.fluid.viscosity)
            self.volume_fraction = np.zeros(mesh.n_local_cells)
            self.flow_knows_id = -1   # particles with larger ids have not been in the flow yet
            self.cfl_warned = False
        self.hydro_force = np.zeros((0, 3))
        self.hydro_torque = np.zeros((0, 3))
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
        progress = Progress(self.comm, run.end_time, self.quiet, start_time=self.time)
        started = wallclock.perf_counter()
        self.write_outputs()
        next_output = (math.floor(self.time / run.output_every + 1e-9) + 1) * run.output_every
        every = run.checkpoint_every
        next_checkpoint = (math.floor(self.time / every + 1e-9) + 1) * every if every else math.inf
        status = "completed"
        checkpoint_time = self.time
        try:
            while self.time < run.end_time * (1 - 1e-12):
                dt = min(run.dt, run.end_time - self.time)
                self.keep_last_good_state()
                self.advance(dt)
                if self.time >= next_output * (1 - 1e-9) or self.time >= run.end_time * (1 - 1e-12):
                    with Timer(self.times, "output"):
                        self.write_outputs()
                    while next_output <= self.time * (1 + 1e-9):
                        next_output += run.output_every
                if self.time >= next_checkpoint * (1 - 1e-9):
                    with Timer(self.times, "checkpoint"):
                        checkpoint.write(self.comm, output, self.mesh, self)
                    checkpoint_time = self.time
                    while next_checkpoint <= self.time * (1 + 1e-9):
                        next_checkpoint += every
                progress.update(self.step, self.time, f"  particles {len(self.particles.id)}")
                if run.wall_time_limit and wallclock.perf_counter() - started > run.wall_time_limit:
                    status = "stopped at the wall-time limit"
                    self.write_outputs()
                    break
            if every and checkpoint_time != self.time:  # the final state, for a later continuation
                with Timer(self.times, "checkpoint"):
                    checkpoint.write(self.comm, output, self.mesh, self)
        except NumericalError:
            status = "numerical failure"
            self.restore_last_good_state()   # SPEC §2: the last good state is written first
            with Timer(self.times, "output"):
                self.write_outputs()
            raise
        finally:
            total = wallclock.perf_counter() - started
            progress.update(self.step, self.time, force=True)
            io.write_summary(self.comm, output, self.summary(status, setup_seconds, total))

    def advance(self, dt: float) -> None:
        """Collective. One time step, stage by stage (ARCHITECTURE.md)."""
        case = self.case
        # 1. inject new particles
        if self.injectors:
            with Timer(self.times, "injection"):
                new = [injector.due(self.time + dt) for injector in self.injectors]
                self.add_particles(NewParticles.concatenate(new))
        state = self.particles
        # 6 (needed by the coupled update). gravity with buoyancy, field forces
        with Timer(self.times, "forces"):
            force = gravity_buoyancy(state, np.array(case.run.gravity), self.fluid_density)
            if case.field_forces is not None:
                force += field_forces_of_case(state, self.walls, case.field_forces)
        torque = np.zeros_like(force)
        if self.flow is not None:
            force, torque = self.flow_step(dt, force, torque)
        # 7. update V and ω, then move, with collisions resolved in time order
        substeps = case.coupling.substeps if self.flow is not None else 1
        for _ in range(substeps):
            with Timer(self.times, "collisions" if self.settings else "motion"):
                accelerate(state, force, torque, dt / substeps)
                if self.settings is not None:
                    stats = advance_with_collisions(state, self.walls, dt / substeps, self.settings)
                    for key, value in stats.items():
                        self.collision_totals[key] = self.collision_totals.get(key, 0) + int(value)
                else:
                    free = state.motion != 1
                    state.x[free] += state.v[free] * dt / substeps
        # 8. particles that left the domain are removed
        with Timer(self.times, "owners"):
            if len(state):
                outside = ~self.inside_domain(state.x)
                if outside.any():
                    self.removed += int(outside.sum())
                    state.remove(outside)
                    if len(self.hydro_force) == len(outside):  # empty without [fluid]
                        self.hydro_force, self.hydro_torque = self.hydro_force[~outside], self.hydro_torque[~outside]
        self.time += dt
        self.step += 1
        check_finite(state, self.step, self.time)

    def flow_step(self, dt: float, force: np.ndarray, torque: np.ndarray):
        """Collective. Steps 2–5: locate, flow with the particles' patch, drag and torque.
        Returns the total force and torque on each particle (external + hydrodynamic)."""
        state, coupling = self.particles, self.coupling
        with Timer(self.times, "coupling"):
            touched = coupling.locate(state)
            fresh = state.id > self.flow_knows_id
            if fresh.any():   # same on every rank: the particles are replicated
                coupling.carry_fluid(state, touched, self.fluid_state.u, fresh)
                self.mesh.update_ghosts(self.fluid_state.u)
                self.flow_knows_id = int(state.id.max())
            if len(state):
                coupling.begin_step(state, touched, self.fluid_state.u)
        hydro = {}

        def patch(u_star, last):
            with Timer(self.times, "coupling"):
                result = coupling.exchange(state, touched, u_star, dt, force, torque, last, self.step, self.time)
                if last:
                    hydro["force"], hydro["torque"] = result

        def penalty():
            with Timer(self.times, "coupling"):
                return coupling.penalty_terms(state, touched)

        with Timer(self.times, "flow"):
            info = self.flow.step(self.fluid_state, dt, patch=patch if len(state) else None,
                                  forcing_iterations=self.case.coupling.forcing_passes,
                                  step=self.step, time=self.time,
                                  penalty=penalty if len(state) and coupling.penalty and coupling.two_way else None)
        self.pressure_iterations = getattr(self, "pressure_iterations", 0) + info["pressure_iterations"]
        self.volume_fraction[:self.mesh.n_owned_cells] = coupling.volume_fraction(touched)
        self.flow.check(self.fluid_state, self.step, self.time)
        if not self.cfl_warned and self.step % 10 == 0:
            cfl = self.flow.cfl(self.fluid_state, dt)
            if cfl > self.case.run.max_cfl:
                if self.comm.rank == 0:
                    warn(self.comm, f"step {self.step}: CFL number {cfl:.2f} exceeds [run] max_cfl = "
                                    f"{self.case.run.max_cfl:g}; the explicit convection may go unstable: reduce [run] dt")
                self.cfl_warned = True
        if not len(state):
            return force, torque
        self.hydro_force, self.hydro_torque = hydro["force"], hydro["torque"]
        return force + hydro["force"], torque + hydro["torque"]

    def keep_last_good_state(self) -> None:
        """Copies of the state at the start of the step, written if the step fails."""
        fluid = self.fluid_state
        self.last_good = (self.time, self.step, copy.deepcopy(self.particles),
                          None if fluid is None else copy.deepcopy(fluid), self.hydro_force, self.hydro_torque)

    def restore_last_good_state(self) -> None:
        (self.time, self.step, self.particles, self.fluid_state,
         self.hydro_force, self.hydro_torque) = self.last_good

    def write_outputs(self) -> None:
        """Collective. One output time: particles.csv rows and a fields.h5 group."""
        state = self.particles
        fields = {}
        if self.flow is not None:
            if len(self.hydro_force) != len(state):
                self.hydro_force, self.hydro_torque = np.zeros((len(state), 3)), np.zeros((len(state), 3))
            fields = {"velocity": self.fluid_state.u, "pressure": self.fluid_state.p,
                      "volume_fraction": self.volume_fraction}
        self.particle_writer.write(self.time, state, self.hydro_force, self.hydro_torque)
        arrays = {"id": state.id, "position": state.x, "velocity": state.v, "angular_velocity": state.omega,
                  "radius": state.radius, "density": state.density}
        self.field_writer.write(self.time, fields, arrays)

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
            *([self.describe_flow()] if self.flow is not None else []),
            f"  setup:     {setup_seconds:.2f} s",
        ])

    def describe_flow(self) -> str:
        """One line on the flow, with the CFL number the boundary velocities give (warns above max_cfl)."""
        fluid, flow, run = self.case.fluid, self.flow, self.case.run
        speed = float(np.linalg.norm(flow.u_fixed, axis=1).max(initial=0.0))
        h = float(flow.h.min(initial=np.inf))
        cfl = self.comm.allreduce(speed * run.dt / h, op=MPI.MAX)
        if cfl > run.max_cfl and self.comm.rank == 0:
            warn(self.comm, f"[run] dt = {run.dt:g} s gives a CFL number of {cfl:.2f} at the boundary velocities "
                            f"(above max_cfl = {run.max_cfl:g}); the explicit convection may go unstable")
        # the paper's patch makes the particle forces depend on ν dt/h² (docs/coupling.md): say it
        diffusion = self.comm.allreduce(fluid.viscosity / fluid.density * run.dt / h ** 2, op=MPI.MAX)
        if diffusion > 1 and (len(self.particles.id) or self.injectors) and self.comm.rank == 0:
            warn(self.comm, f"[run] dt = {run.dt:g} s gives ν dt/h² = {diffusion:.3g}: above 1 the drag on "
                            "particles falls with dt, the more so the fewer cells per diameter (docs/coupling.md); "
                            "a smaller dt keeps it")
        self.warn_outside_validation(speed)
        return (f"  flow:      ρ = {fluid.density:g} kg/m³, μ = {fluid.viscosity:g} Pa s, {fluid.convection} "
                f"convection, CFL at boundary speeds {cfl:.2f}, ν dt/h² {diffusion:.3g}; coupling "
                f"{self.case.coupling.mode}, {self.case.coupling.forcing} forcing, "
                f"{self.case.coupling.volume_fraction} volume fraction, {self.case.coupling.update} update, "
                f"{self.case.coupling.forcing_passes} forcing passes")

    def warn_outside_validation(self, boundary_speed: float) -> None:
        """Collective. Warn where particles are resolved more coarsely, or may meet the flow at a higher
        Reynolds number, than the coupling was validated for (bench/drag_curve.py, docs/coupling.md):
        fewer than 3 cells per diameter; Re above 1000; Re above (d/h)², where the boundary layer,
        about d/√Re thick, is thinner than a cell and the drag comes out too high. The relative speed
        is bounded by the boundary velocities, the particles' own and their settling speed in still
        fluid (Schiller–Naumann)."""
        from .reference import terminal_velocity

        state, fluid, mesh = self.particles, self.case.fluid, self.mesh
        boundary_speed = self.comm.allreduce(boundary_speed, op=MPI.MAX)
        h_max = self.comm.allreduce(float(self.flow.h[:mesh.n_owned_cells].max(initial=0.0)), op=MPI.MAX)
        gravity = float(np.linalg.norm(self.case.run.gravity))
        # present particles: h of the cell holding the centre; injected ones: the coarsest cell
        cells = mesh.find_owned_cells(state.x)
        h = np.where(cells >= 0, self.flow.h[np.maximum(cells, 0)], 0.0)
        if self.comm.size > 1:
            self.comm.Allreduce(MPI.IN_PLACE, h, op=MPI.MAX)
        diameter = np.concatenate([2 * state.radius, [2 * i.section.radius for i in self.injectors]])
        density = np.concatenate([state.density, [i.section.density for i in self.injectors]])
        own_speed = np.concatenate([np.linalg.norm(state.v, axis=1),
                                    [np.linalg.norm(i.section.velocity) for i in self.injectors]])
        free = np.concatenate([state.motion == 0, np.ones(len(self.injectors), bool)])
        h = np.concatenate([np.where(h > 0, h, h_max), np.full(len(self.injectors), h_max)])
        if not len(diameter) or self.comm.rank:
            return
        settling = np.zeros(len(diameter))
        sinking = free & (density != fluid.density) & (gravity > 0)
        settling[sinking] = terminal_velocity(density[sinking], fluid.density, fluid.viscosity, diameter[sinking],
                                              gravity)
        reynolds = fluid.density * np.maximum.reduce([np.full(len(diameter), boundary_speed), own_speed, settling]) \
            * diameter / fluid.viscosity
        resolution = diameter / h
        if resolution.min() < 3:
            warn(self.comm, f"{int((resolution < 3).sum())} particle(s) span fewer than 3 cells per diameter (down to "
                            f"{resolution.min():.2g}): the coupling's drag and blockage are validated from 3 on "
                            "(docs/coupling.md)")
        worst = int(np.argmax(reynolds / resolution ** 2))
        if reynolds.max() > 1000:
            warn(self.comm, f"particles may meet the flow at Re ≈ {reynolds.max():.3g} (boundary, particle and settling "
                            "speeds): the drag is validated up to Re 1000 (docs/coupling.md)")
        elif reynolds[worst] > resolution[worst] ** 2:
            warn(self.comm, f"particles may meet the flow at Re ≈ {reynolds[worst]:.3g} on {resolution[worst]:.2g} "
                            f"cells per diameter: above Re = (d/h)² the boundary layer (≈ d/√Re) is thinner than a "
                            "cell and the drag comes out too high (docs/coupling.md: its error by Re and resolution)")

    def summary(self, status: str, setup_seconds: float, total_seconds: float) -> dict:
        state = self.particles
        return {
            "case": str(self.case.path), "status": status, "ranks": self.comm.size,
            "cells": self.mesh.n_global_cells, "particles": len(state.id), "particles_removed": self.removed,
            "steps": self.step, "simulated_time": self.time, "models": self.case.models(),
            "wall_seconds": {"total": total_seconds, "setup": setup_seconds, **self.times.seconds},
            "diagnostics": self.diagnostics(),
        }

    def diagnostics(self) -> dict:
        """Collective. Conservation checks for summary.json."""
        state = self.particles
        result = {"particle_kinetic_energy": 0.5 * float(np.sum(state.mass * np.sum(state.v ** 2, axis=1))),
                  "particle_momentum": (state.mass[:, None] * state.v).sum(axis=0)}
        if self.settings is not None:
            result["collisions"] = dict(self.collision_totals)
        if self.flow is not None:
            flow, fluid = self.flow, self.fluid_state
            owned = slice(0, self.mesh.n_owned_cells)
            momentum = self.fluid_density * (self.mesh.cell_volume[owned, None] * fluid.u[owned]).sum(axis=0)
            fluxes = flow.boundary_flux(fluid)
            result.update({
                "fluid_kinetic_energy": flow.kinetic_energy(fluid),
                "fluid_momentum": allreduce_sum(self.comm, momentum),
                "max_divergence_per_second": flow.divergence_norm(fluid),
                "boundary_volume_flux": fluxes,
                "net_volume_flux": sum(fluxes.values()),
                "pressure_iterations": getattr(self, "pressure_iterations", 0),
                "final_cfl": flow.cfl(fluid, self.case.run.dt),
            })
        return result


def check_finite(state, step: int, time: float) -> None:
    """Raise NumericalError naming the first particle whose state is not finite."""
    bad = ~np.isfinite(state.x).all(axis=1) | ~np.isfinite(state.v).all(axis=1)
    if bad.any():
        pid = int(state.id[np.argmax(bad)])
        raise NumericalError(f"step {step}, t = {time:.6g} s: particle {pid} has a non-finite position or "
                             "velocity; reduce [run] dt")
