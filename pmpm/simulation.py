"""The time loop: the pieces a case asks for, one time step as a sequence of stages, and the run.

A section absent from the case builds nothing (``build_model``), and its stages cost nothing. Every
stage takes the run state (``pmpm.state.RunState``) and returns a new one; ``advance`` is one step,
top to bottom, and ``run`` repeats it, writing outputs and checkpoints on the way.
"""
from __future__ import annotations

import math
import time as wallclock
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from . import checkpoint, checks, io, reporting
from .case import Case, case_path, load_case, suggest
from .collisions import (CollisionSettings, advance_with_collisions, build_walls, check_initial_particles,
                         collision_settings, overlaps_existing)
from .coupling import CouplingMemory, External, PatchForcing, PenaltyForcing, build_forcing, volume_fraction
from .errors import CaseError, NumericalError
from .fluid import FlowSolver
from .forces import field_forces_of_case, gravity_buoyancy
from .injection import Injector, NewParticles, build_injectors, initial_particles
from .mesh import Mesh
from .parallel import print0
from .particles import FIXED, ParticleState, accelerate
from .reporting import StageTimes
from .state import RunState


# ----------------------------------------------------------------------------------------------
# Building: the fixed pieces of a run, and its first state
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Model:
    """What a case asks for, built once: mesh, flow solver, forcing, injectors, contact settings
    (None where the case's section is absent). Collective objects keep ``comm``."""

    comm: object
    case: Case
    mesh: Mesh
    flow: FlowSolver | None
    forcing: PenaltyForcing | PatchForcing | None
    injectors: tuple[Injector, ...]
    contact_settings: CollisionSettings | None

    @property
    def fluid_density(self) -> float:
        return self.case.fluid.density if self.case.fluid is not None else 0.0


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


def build_model(comm, case: Case, mesh: Mesh) -> Model:
    """Collective. The pieces of ``case`` on ``mesh``."""
    flow = forcing = None
    if case.fluid is not None:
        flow = FlowSolver(mesh, case.fluid, case.boundaries)
        forcing = build_forcing(mesh, case.coupling, case.fluid)
    return Model(comm, case, mesh, flow, forcing, build_injectors(case),
                 collision_settings(case) if case.collisions else None)


def initial_state(model: Model) -> RunState:
    """Collective. The state at t = 0: fluid at rest, the case's particles (checked: inside the
    domain, not overlapping each other or a wall)."""
    case, mesh = model.case, model.mesh
    walls = build_walls(case, mesh) if (case.collisions or case.field_forces or case.deposition) else None
    fluid = model.flow.initial_state() if model.flow is not None else None
    state = RunState(0.0, 0, ParticleState.empty(), fluid, np.zeros((0, 3)), np.zeros((0, 3)),
                     np.zeros(mesh.n_local_cells) if fluid is not None else None, next_id=0, removed=0,
                     releases=(0,) * len(model.injectors), coupling=CouplingMemory() if fluid is not None else None,
                     walls=walls)
    return add_particles(model, state, initial_particles(case), validate=True)


def add_particles(model: Model, state: RunState, new: NewParticles, validate: bool = False) -> RunState:
    """Collective. ``state`` with the ``new`` particles that lie in the domain, with fresh ids.
    ``validate`` (the case's own particles): any outside the domain, or overlapping another particle
    or a wall, is a CaseError; otherwise (injections) such releases are skipped."""
    if len(new) == 0:
        return state
    inside = model.mesh.inside_domain(new.x)
    if validate:
        check_initial_particles(model.case, new, inside, state.walls)
    keep = inside if validate else inside & ~overlaps_existing(state.particles, new)
    n = int(keep.sum())
    particles = state.particles.appended(state.next_id + np.arange(n), new.x[keep], new.v[keep], new.omega[keep],
                                         new.radius[keep], new.density[keep], new.motion[keep])
    return replace(state, particles=particles, next_id=state.next_id + n,
                   hydro_force=np.concatenate([state.hydro_force, np.zeros((n, 3))]),
                   hydro_torque=np.concatenate([state.hydro_torque, np.zeros((n, 3))]))


# ----------------------------------------------------------------------------------------------
# One time step
# ----------------------------------------------------------------------------------------------
def advance(model: Model, state: RunState, dt: float, times: StageTimes) -> RunState:
    """Collective. One time step, stage by stage (ARCHITECTURE.md)."""
    # 1. inject new particles
    if model.injectors:
        with times.stage("injection"):
            state = inject(model, state, state.time + dt)
    # 6, needed by the coupled update: gravity with buoyancy, field forces
    with times.stage("forces"):
        external = external_forces(model, state)
    # 2–5. locate the particles' cells, advance the flow with their forcing, drag and torque
    force, torque = external.force, external.torque
    if model.flow is not None:
        state = flow_stage(model, state, external, dt, times)
        force, torque = force + state.hydro_force, torque + state.hydro_torque
    # 7. update V and ω, then move, with collisions resolved in time order
    with times.stage("collisions" if model.contact_settings is not None else "motion"):
        state = move_particles(model, state, force, torque, dt)
    # 8. particles that left the domain are removed
    with times.stage("owners"):
        state = remove_outside(model, state)
    state = replace(state, time=state.time + dt, step=state.step + 1)
    check_finite(state.particles, state.step, state.time)
    return state


def inject(model: Model, state: RunState, time_end: float) -> RunState:
    """Collective. The releases of every injection due by ``time_end``."""
    parts, releases = [], []
    for injector, next_release in zip(model.injectors, state.releases):
        new, next_release = injector.due(next_release, time_end)
        parts.append(new)
        releases.append(next_release)
    return add_particles(model, replace(state, releases=tuple(releases)), NewParticles.concatenate(parts))


def external_forces(model: Model, state: RunState) -> External:
    """Gravity less buoyancy and the field forces (eq. 9–10) on each particle; no torque."""
    case, particles = model.case, state.particles
    force = gravity_buoyancy(particles, np.array(case.run.gravity), model.fluid_density)
    if case.field_forces is not None:
        force += field_forces_of_case(particles, state.walls, case.field_forces)
    return External(force, np.zeros_like(force))


def flow_stage(model: Model, state: RunState, external: External, dt: float, times: StageTimes) -> RunState:
    """Collective. Steps 2–5: the particles' touched cells, the flow advanced with their forcing
    (``forcing_passes`` momentum solves, the forcing updating its guess of the particles' motion
    after each), the projection, and the fluid's force and torque on each particle."""
    flow, forcing, particles = model.flow, model.forcing, state.particles
    n_owned = model.mesh.n_owned_cells
    step, time = state.step, state.time
    coupled = len(particles) > 0
    passes = model.case.coupling.forcing_passes if coupled else 1
    fluid = state.fluid
    with times.stage("coupling"):
        touched = forcing.locate(particles)
        if coupled:
            forcing_state, fluid = forcing.begin(particles, touched, fluid, state.coupling, dt)
    with times.stage("flow"):
        predicted = flow.predictor(fluid, dt)
    rhs, u_star = predicted.rhs, fluid.u
    for forcing_pass in range(passes):
        diagonal = target = None
        if coupled:
            with times.stage("coupling"):
                diagonal, target = forcing.implicit_terms(particles, forcing_state)
        with times.stage("flow"):
            u_star = flow.solve_momentum(rhs if target is None else plus_owned(rhs, target), u_star, dt, step, time,
                                         extra_diagonal=diagonal)
        if coupled:
            with times.stage("coupling"):
                u_star, source, forcing_state = forcing.after_solve(particles, forcing_state, u_star, external, dt)
            if source is not None and forcing_pass < passes - 1:
                rhs = plus_owned(rhs, source)
    with times.stage("flow"):
        projection = flow.project(fluid, u_star, predicted, dt, step, time)
        fluid = flow.correct(fluid, u_star, projection, dt)
    with times.stage("coupling"):
        fractions = np.zeros(model.mesh.n_local_cells)
        fractions[:n_owned] = volume_fraction(touched, n_owned)
        state = replace(state, fluid=fluid, volume_fraction=fractions,
                        pressure_iterations=state.pressure_iterations + projection.iterations)
        if coupled:
            exchange = forcing.after_projection(particles, forcing_state, fluid, external, dt, state.coupling,
                                                step, time)
            state = replace(state, fluid=exchange.fluid, hydro_force=exchange.force, hydro_torque=exchange.torque,
                            coupling=exchange.memory)
    flow.check(state.fluid, step, time)
    return state


def plus_owned(array: np.ndarray, owned_rows: np.ndarray) -> np.ndarray:
    """A copy of ``array`` with ``owned_rows`` added to its first rows (the owned cells')."""
    out = array.copy()
    out[:len(owned_rows)] += owned_rows
    return out


def move_particles(model: Model, state: RunState, force: np.ndarray, torque: np.ndarray, dt: float) -> RunState:
    """Newton–Euler update of V and ω, then the motion over dt with contacts resolved in time
    order (``[coupling] substeps`` times with a flow)."""
    substeps = model.case.coupling.substeps if model.flow is not None else 1
    particles = state.particles.copy()
    walls, contacts, totals = state.walls, state.contacts, state.collision_totals
    for _ in range(substeps):
        accelerate(particles, force, torque, dt / substeps)
        if model.contact_settings is not None:
            result = advance_with_collisions(particles, walls, dt / substeps, model.contact_settings, contacts)
            walls, contacts = result.walls, result.memory
            totals = {**totals, **{key: totals.get(key, 0) + int(value) for key, value in result.stats.items()}}
        else:
            free = particles.motion != FIXED
            particles.x[free] += particles.v[free] * dt / substeps
    return replace(state, particles=particles, walls=walls, contacts=contacts, collision_totals=totals)


def remove_outside(model: Model, state: RunState) -> RunState:
    """Collective. Particles whose centre left the domain are removed (counted in ``removed``)."""
    if len(state.particles) == 0:
        return state
    outside = ~model.mesh.inside_domain(state.particles.x)
    if not outside.any():
        return state
    return replace(state, particles=state.particles.without(outside), removed=state.removed + int(outside.sum()),
                   hydro_force=state.hydro_force[~outside], hydro_torque=state.hydro_torque[~outside])


def check_finite(particles: ParticleState, step: int, time: float) -> None:
    """Raise NumericalError naming the first particle whose state is not finite."""
    bad = ~np.isfinite(particles.x).all(axis=1) | ~np.isfinite(particles.v).all(axis=1)
    if bad.any():
        pid = int(particles.id[np.argmax(bad)])
        raise NumericalError(f"step {step}, t = {time:.6g} s: particle {pid} has a non-finite position or "
                             "velocity; reduce [run] dt")


# ----------------------------------------------------------------------------------------------
# The run
# ----------------------------------------------------------------------------------------------
class Simulation:
    """A model and its current run state: ``advance`` steps it, ``run`` runs the case to its end.
    Collective. For scripts and tests the state's parts are at hand as attributes."""

    def __init__(self, comm, case: Case, mesh: Mesh, quiet: bool = False, state: RunState | None = None):
        self.comm, self.quiet = comm, quiet
        self.model = build_model(comm, case, mesh)
        self.state = initial_state(self.model) if state is None else state
        self.times = StageTimes()

    def advance(self, dt: float) -> None:
        """Collective. One time step of the current state."""
        self.state = advance(self.model, self.state, dt, self.times)

    case = property(lambda self: self.model.case)
    mesh = property(lambda self: self.model.mesh)
    flow = property(lambda self: self.model.flow)
    forcing = property(lambda self: self.model.forcing)
    time = property(lambda self: self.state.time)
    particles = property(lambda self: self.state.particles)
    fluid_state = property(lambda self: self.state.fluid)
    hydro_force = property(lambda self: self.state.hydro_force)
    hydro_torque = property(lambda self: self.state.hydro_torque)

    def describe_flow(self) -> str:
        return reporting.describe_flow(self.model, self.state)

    def run(self, output: Path, setup_seconds: float) -> None:
        """Collective. Run to end_time (or the wall-time limit), writing outputs on the way; on a
        numerical failure the state the failed step started from is written first (exit 3)."""
        model, run = self.model, self.model.case.run
        writers = io.Writers.open(self.comm, output, model.mesh, model.flow is not None)
        progress = reporting.Progress(self.comm, run.end_time, self.quiet, start_time=self.state.time)
        started = wallclock.perf_counter()
        writers.write(self.state)
        next_output = (math.floor(self.state.time / run.output_every + 1e-9) + 1) * run.output_every
        every = run.checkpoint_every
        next_checkpoint = (math.floor(self.state.time / every + 1e-9) + 1) * every if every else math.inf
        status = "completed"
        checkpoint_time = self.state.time
        cfl_warned = False
        try:
            while self.state.time < run.end_time * (1 - 1e-12):
                dt = min(run.dt, run.end_time - self.state.time)
                self.advance(dt)   # on a NumericalError self.state stays the state the step started from
                time = self.state.time
                if self.state.step % 10 == 1:
                    cfl_warned = reporting.warn_on_cfl(model, self.state, cfl_warned)
                if time >= next_output * (1 - 1e-9) or time >= run.end_time * (1 - 1e-12):
                    with self.times.stage("output"):
                        writers.write(self.state)
                    while next_output <= time * (1 + 1e-9):
                        next_output += run.output_every
                if time >= next_checkpoint * (1 - 1e-9):
                    with self.times.stage("checkpoint"):
                        checkpoint.write(self.comm, output, model.mesh, self.state)
                    checkpoint_time = time
                    while next_checkpoint <= time * (1 + 1e-9):
                        next_checkpoint += every
                progress.update(self.state.step, time, f"  particles {len(self.state.particles)}")
                if run.wall_time_limit and wallclock.perf_counter() - started > run.wall_time_limit:
                    status = "stopped at the wall-time limit"
                    writers.write(self.state)
                    break
            if every and checkpoint_time != self.state.time:  # the final state, for a later continuation
                with self.times.stage("checkpoint"):
                    checkpoint.write(self.comm, output, model.mesh, self.state)
        except NumericalError:
            status = "numerical failure"
            with self.times.stage("output"):   # the last good state is written first
                writers.write(self.state)
            raise
        finally:
            total = wallclock.perf_counter() - started
            progress.update(self.state.step, self.state.time, force=True)
            seconds = {"total": total, "setup": setup_seconds, **self.times.seconds}
            io.write_summary(self.comm, output, reporting.summary(model, self.state, status, seconds))


def run_from_arguments(comm, arguments) -> None:
    """Collective. Everything ``python -m pmpm`` does after parsing the command line."""
    case = load_case(case_path(arguments.case), arguments.set)
    output = Path(arguments.output) if arguments.output else case.folder / "output"
    checks.before_building(comm, case)
    restart = checkpoint.read(comm, Path(arguments.restart)) if arguments.restart else None
    start = wallclock.perf_counter()
    mesh = build_mesh(comm, case)
    check_boundaries(case, mesh)
    simulation = Simulation(comm, case, mesh, quiet=arguments.quiet)
    if restart is not None:
        simulation.state = checkpoint.restore(comm, restart, simulation.model, simulation.state,
                                              Path(arguments.restart))
        print0(comm, f"pmpm: restarting from {arguments.restart} at t = {simulation.state.time:g} s, "
                     f"step {simulation.state.step}")
    writes = checks.before_running(comm, simulation.model, simulation.state, output, arguments.restart)
    setup_seconds = wallclock.perf_counter() - start
    print0(comm, reporting.describe(simulation.model, simulation.state, setup_seconds))
    print0(comm, writes)
    if arguments.check:
        return
    moved = io.prepare_output_folder(comm, output.resolve())
    if moved is not None:
        print0(comm, f"pmpm: the earlier results in {output} were kept as {moved}")
    simulation.run(output.resolve(), setup_seconds)
