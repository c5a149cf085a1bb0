"""The time loop: the pieces a case asks for, one time step as a sequence of stages, and the run.

A section absent from the case builds nothing (``build_model``), and its stages cost nothing. Every
stage takes the run state (``pmpm.state.RunState``) and returns a new one; ``advance`` is one step,
top to bottom, and ``run`` repeats it, writing outputs and checkpoints on the way.
"""
from __future__ import annotations

import math
import signal
import time as wallclock
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from mpi4py import MPI

from . import checkpoint, checks, io, reporting
from .bodies import Body, build_bodies
from .case import Case, case_path, load_case, suggest
from .collisions import (CollisionSettings, advance_with_collisions, build_walls, check_initial_particles,
                         collision_settings, jit)
from .collisions.subdomains import advance_owned
from .coupling import CouplingMemory, External, PatchForcing, PenaltyForcing, build_forcing
from .coupling.bodies import BodyForcing
from .errors import CaseError, NumericalError, Stopped
from .exits import BoundaryFaces
from .fluid import FlowSolver
from .forces import field_forces_of_case, gravity_buoyancy
from .injection import Injector, NewParticles, build_injectors, initial_particles
from .placement import place_releases
from .mesh import Mesh
from .flow_stage import flow_stage
from .migration import check_finite, migrate_particles, remove_outside
from .ownership import Partition, bisect, gather, gather_with
from .parallel import agree, print0
from .particles import FIXED, ParticleState, accelerate
from .reporting import StageTimes
from .signals import StopRequests, stop_message
from .state import RunState
from .timestep import FlowWatch, next_time_step, watch_flow


# ----------------------------------------------------------------------------------------------
# Building: the fixed pieces of a run, and its first state
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Model:
    """What a case asks for, built once: mesh, flow solver, forcing, injectors, contact settings,
    immersed bodies and their forcing (None where the case's section is absent). Collective
    objects keep ``comm``."""

    comm: object
    case: Case
    mesh: Mesh
    flow: FlowSolver | None
    forcing: PenaltyForcing | PatchForcing | None
    injectors: tuple[Injector, ...]
    contact_settings: CollisionSettings | None
    bodies: tuple[Body, ...] = ()
    body_forcing: BodyForcing | None = None
    exits: BoundaryFaces | None = None    # where particles can be: the boundary they leave through
    cell_boxes: Partition | None = None   # ranks owning particles in a flow: each rank's owned cells' extent
    coupling_reach: float = 0.0           # ... and how far beyond a sphere the forcing reaches a cell (m)

    @property
    def fluid_density(self) -> float:
        return self.case.fluid.density if self.case.fluid is not None else 0.0

    @property
    def owns_particles(self) -> bool:
        """Whether each rank holds only the particles it owns (``pmpm.ownership``): any run on several
        ranks. Without a flow the boxes are bisected over the particles; with one they are the
        mesh's own (``Mesh.part_boxes``), so a particle belongs to the rank of its centre's cell."""
        return self.comm.size > 1


def build_mesh(comm, case: Case) -> Mesh:
    """Collective. The case's mesh, distributed over ``comm``: where particles start in a flow,
    with their coupling work shared among the ranks as well as the cells (``pmpm.partition``)."""
    work = error = None
    if comm.size > 1 and case.fluid is not None and case.particles is not None:
        try:
            if comm.rank == 0:   # a pair's work scales as the cells a particle covers
                particles = initial_particles(case)
                work = (particles.x, particles.radius ** 3)
        except CaseError as exc:   # (a bad particle file: every rank leaves)
            error = exc
        agree(comm, error)
    if case.box is not None:
        patches = [(p.name, p.side, p.lower, p.upper) for p in case.patches]
        return Mesh.from_box(comm, case.box.lower, case.box.upper, case.box.cells, case.mesh.cell_type, patches, work)
    return Mesh.from_file(comm, case.resolve(case.mesh.file), work)


def check_boundaries(case: Case, mesh: Mesh) -> None:
    """Every [boundary.<name>] and deposition zone must name a boundary of the mesh (a zone may name a body)."""
    names = list(mesh.boundary_names)
    listed = [(f"[boundary.{n}]", n) for n in case.boundaries]
    bodies = {body.name for body in case.bodies}   # particles may stick to a named body too
    listed += [("[deposition] zones", n) for n in (case.deposition.zones if case.deposition else ()) if n not in bodies]
    for where, name in listed:
        if name not in names:
            raise CaseError(f"{case.path.name}: {where}: the mesh has no boundary \"{name}\"{suggest(name, names)}"
                            f" (it has: {', '.join(names)})")


def build_model(comm, case: Case, mesh: Mesh) -> Model:
    """Collective. The pieces of ``case`` on ``mesh``."""
    flow = forcing = body_forcing = None
    bodies = build_bodies(case)
    if case.fluid is not None:
        flow = FlowSolver(mesh, case.fluid, case.boundaries)
        corrected = case.coupling.drag_correction != "off"
        forcing = build_forcing(mesh, case.coupling, case.fluid, largest_diameter(case) if corrected else 0.0)
        if bodies:
            body_forcing = BodyForcing(mesh, bodies, case.coupling, case.fluid.density, case.fluid.viscosity)
    exits = BoundaryFaces.of_mesh(mesh) if (case.particles is not None or case.injections) else None
    cell_boxes, reach = None, 0.0
    if flow is not None and comm.size > 1:
        corners = mesh.vertex_xyz[mesh.cell_vertices[:mesh.n_owned_cells]].reshape(-1, 3)
        extents = comm.allgather((corners.min(axis=0, initial=np.inf), corners.max(axis=0, initial=-np.inf)))
        cell_boxes = Partition(np.array([low for low, _ in extents]), np.array([high for _, high in extents]))
        reach = comm.allreduce(float(forcing.locator.search_reach.max(initial=0.0)), op=MPI.MAX)
    return Model(comm, case, mesh, flow, forcing, build_injectors(case),
                 collision_settings(case) if case.collisions else None, bodies, body_forcing, exits,
                 cell_boxes, reach)


def largest_diameter(case: Case) -> float:
    """The largest particle diameter (m) among the case's particles and injections (0 if none)."""
    radii = [float(initial_particles(case).radius.max(initial=0.0))]
    radii += [injection.radius for injection in case.injections]
    return 2.0 * max(radii)


def has_walls(case: Case) -> bool:
    """Whether the particles of ``case`` meet walls (collisions, field forces, deposition): the run
    then builds them, and loads (or first compiles) the contact kernels."""
    return bool(case.collisions or case.field_forces or case.deposition)


def initial_state(model: Model, case_particles: bool = True) -> RunState:
    """Collective. The state at t = 0: fluid at rest, the case's particles (checked: inside the
    domain, not overlapping each other or a wall); without ``case_particles`` none (a restart,
    whose checkpoint holds the particles: checking the case's would take a quarter of a second
    per 10,000)."""
    case, mesh = model.case, model.mesh
    walls = build_walls(case, mesh, model.bodies) if has_walls(case) else None
    fluid = model.flow.initial_state() if model.flow is not None else None
    state = RunState(0.0, 0, ParticleState.empty(), fluid, np.zeros((0, 3)), np.zeros((0, 3)),
                     np.zeros(mesh.n_local_cells) if fluid is not None else None, next_id=0, removed=0,
                     releases=(0,) * len(model.injectors), coupling=CouplingMemory() if fluid is not None else None,
                     walls=walls)
    if case_particles:
        state = add_particles(model, state, initial_particles(case), validate=True)
    return distribute(model, replace(state, fresh_from=state.next_id))


def distribute(model: Model, state: RunState) -> RunState:
    """Collective. Where ranks own particles (``Model.owns_particles``): the case's particles, which
    every rank read whole, as each rank's own, in the mesh's boxes (a flow) or in boxes bisected
    over them. Otherwise the state."""
    if not model.owns_particles:
        return state
    return state.owned_by(model.comm.rank, particle_boxes(model, state.particles.x))


def particle_boxes(model: Model, x: np.ndarray) -> Partition:
    """Collective. The boxes whose ranks own the particles at ``x`` (every rank's, (n, 3)): with a
    flow the mesh's (fixed), without one bisected over the particles (``ownership.bisect``)."""
    comm, mesh = model.comm, model.mesh
    if model.flow is not None:
        return Partition(mesh.part_boxes[0], mesh.part_boxes[1])
    return bisect(comm, x if comm.rank == 0 else np.zeros((0, 3)), (mesh.lower, mesh.upper))


def add_particles(model: Model, state: RunState, new: NewParticles, validate: bool = False) -> RunState:
    """Collective. ``state`` with the ``new`` particles, with fresh ids. ``validate`` (the case's own
    particles): any outside the domain, or overlapping another particle or a wall, is a CaseError."""
    if len(new) == 0:
        return state
    if validate:
        check_initial_particles(model.case, new, model.mesh.inside_domain(new.x), state.walls)
    n = len(new)
    mine = np.ones(n, bool)
    if state.partition is not None:   # every rank took the same decision: each keeps its own
        mine = state.partition.owner_of(new.x) == model.comm.rank
    k = int(mine.sum())
    particles = state.particles.appended(state.next_id + np.flatnonzero(mine), new.x[mine], new.v[mine],
                                         new.omega[mine], new.radius[mine], new.density[mine], new.motion[mine])
    return replace(state, particles=particles, next_id=state.next_id + n,
                   hydro_force=np.concatenate([state.hydro_force, np.zeros((k, 3))]),
                   hydro_torque=np.concatenate([state.hydro_torque, np.zeros((k, 3))]))


# ----------------------------------------------------------------------------------------------
# One time step
# ----------------------------------------------------------------------------------------------
def advance(model: Model, state: RunState, dt: float, times: StageTimes) -> RunState:
    """Collective. One time step, stage by stage (ARCHITECTURE.md)."""
    # 6, needed by the coupled update: gravity with buoyancy, field forces
    with times.stage("forces"):
        external = external_forces(model, state)
    # 2–5. locate the particles' cells, advance the flow with their forcing, drag and torque
    force, torque = external.force, external.torque
    if model.flow is not None:
        state = flow_stage(model, state, external, dt, times)
        force, torque = force + state.hydro_force, torque + state.hydro_torque
    # 7. update V and ω, then move, with collisions resolved in time order
    moved_from = state.particles.x
    with times.stage("collisions" if model.contact_settings is not None else "motion"):
        state = move_particles(model, state, force, torque, dt)
    # 8. particles that left the domain are removed; particles whose centre changed rank migrate
    with times.stage("owners"):
        state = remove_outside(model.exits, state, moved_from) if state.partition is None else \
            migrate_particles(model.comm, model.exits, state, moved_from, dt, rebalance=model.flow is None)
    # 1 (of the next step). particles released within this step, where they are at its end
    state = replace(state, fresh_from=state.next_id)
    if model.injectors:
        with times.stage("injection"):
            state = inject(model, state, state.time + dt)
    state = replace(state, time=state.time + dt, step=state.step + 1, dt=dt)
    if state.partition is None:   # (else checked by migrate_particles)
        check_finite(state.particles, state.step, state.time)
    return state


def inject(model: Model, state: RunState, time_end: float) -> RunState:
    """Collective. The releases of every injection due by ``time_end``, each particle where its
    release velocity has taken it by then (released at t, it flies time_end − t), placed clear of
    the walls and the other particles (``pmpm.placement``; its counts are summed in the state)."""
    parts, releases = [], []
    for injector, next_release in zip(model.injectors, state.releases):
        new, next_release = injector.due(next_release, time_end)
        parts.append(new)
        releases.append(next_release)
    state = replace(state, releases=tuple(releases))
    new = NewParticles.concatenate(parts)
    if len(new) == 0:
        return state
    flight = new.v * (time_end - new.release_times)[:, None]
    new = replace(new, x=new.x + flight, alternatives=new.other_positions + flight)
    placement = place_releases(model.mesh, state.particles, state.walls, new)
    totals = {key: state.injection_counts.get(key, 0) + value for key, value in placement.counts.items()}
    return replace(add_particles(model, state, placement.placed), injection_counts=totals)


def external_forces(model: Model, state: RunState) -> External:
    """Gravity less buoyancy and the field forces (eq. 9–10) on each particle; no torque."""
    case, particles = model.case, state.particles
    force = gravity_buoyancy(particles, np.array(case.run.gravity), model.fluid_density)
    if case.field_forces is not None:
        force += field_forces_of_case(particles, state.walls, case.field_forces, model.comm, state.partition)
    return External(force, np.zeros_like(force))


def move_particles(model: Model, state: RunState, force: np.ndarray, torque: np.ndarray, dt: float) -> RunState:
    """Newton–Euler update of V and ω, then the motion over dt with contacts resolved in time
    order (``[coupling] substeps`` times with a flow)."""
    substeps = model.case.coupling.substeps if model.flow is not None else 1
    particles = state.particles.copy()
    walls, contacts, totals = state.walls, state.contacts, state.collision_totals
    for _ in range(substeps):
        accelerate(particles, force, torque, dt / substeps)
        if model.contact_settings is not None:
            if state.partition is not None:
                result = advance_owned(model.comm, state.partition, particles, walls, dt / substeps,
                                       model.contact_settings, contacts)
                seen = {key: max(state.ranks_seen.get(key, 0), result.stats.pop(key))
                        for key in ("owned", "ghosts", "exchanged_bytes")}
                state = replace(state, ranks_seen=seen)
            else:
                result = advance_with_collisions(particles, walls, dt / substeps, model.contact_settings, contacts)
            walls, contacts = result.walls, result.memory
            totals = {**totals, **{key: totals.get(key, 0) + int(value) for key, value in result.stats.items()}}
        else:
            free = particles.motion != FIXED
            particles.x[free] += particles.v[free] * dt / substeps
    return replace(state, particles=particles, walls=walls, contacts=contacts, collision_totals=totals)


# ----------------------------------------------------------------------------------------------
# The run
# ----------------------------------------------------------------------------------------------
class Simulation:
    """A model and its current run state: ``advance`` steps it, ``run`` runs the case to its end.
    Collective. For scripts and tests the state's parts are at hand as attributes."""

    def __init__(self, comm, case: Case, mesh: Mesh, quiet: bool = False, state: RunState | None = None,
                 case_particles: bool = True):
        self.comm, self.quiet = comm, quiet
        self.model = build_model(comm, case, mesh)
        self.state = initial_state(self.model, case_particles) if state is None else state
        self.times = StageTimes()

    def advance(self, dt: float) -> None:
        """Collective. One time step of the current state."""
        self.state = advance(self.model, self.state, dt, self.times)

    case = property(lambda self: self.model.case)
    mesh = property(lambda self: self.model.mesh)
    flow = property(lambda self: self.model.flow)
    forcing = property(lambda self: self.model.forcing)
    time = property(lambda self: self.state.time)
    @property
    def particles(self) -> ParticleState:
        """Every particle (collective where ranks own particles: gathered, in id order)."""
        return gather(self.comm, self.state.particles) if self.state.partition is not None else self.state.particles

    fluid_state = property(lambda self: self.state.fluid)
    @property
    def hydro_force(self) -> np.ndarray:
        """The fluid's force on every particle (collective where ranks own particles: in id order)."""
        return self._hydro()[0]

    @property
    def hydro_torque(self) -> np.ndarray:
        """The fluid's torque on every particle (collective where ranks own particles: in id order)."""
        return self._hydro()[1]

    def _hydro(self):
        state = self.state
        if state.partition is None:
            return state.hydro_force, state.hydro_torque
        return gather_with(self.comm, state.particles, state.hydro_force, state.hydro_torque)[1:]

    def describe_flow(self) -> str:
        return reporting.describe_flow(self.model, self.state)

    def run(self, output: Path, setup_seconds: float) -> None:
        """Collective. Run to end_time, writing outputs and checkpoints on the way. Stops early, its
        state written, at the wall-time limit or on SIGTERM/SIGINT (``Stopped``, after a checkpoint);
        on a numerical failure or a diverging flow (``NumericalError``) the last good state is
        written first."""
        model, run = self.model, self.model.case.run
        writers = io.Writers.open(self.comm, output, model.mesh, model.flow is not None,
                                  tuple(body.name for body in model.bodies))
        progress = reporting.Progress(self.comm, run.end_time, self.quiet, start_time=self.state.time)
        started = wallclock.perf_counter()
        writers.write(self.state)
        next_output = (math.floor(self.state.time / run.output_every + 1e-9) + 1) * run.output_every
        every = run.checkpoint_every
        next_checkpoint = (math.floor(self.state.time / every + 1e-9) + 1) * every if every else math.inf
        status, stop = "completed", None
        checkpoint_time = self.state.time
        watch = FlowWatch(self.state, model.flow.boundary_cfl(run.dt) if model.flow is not None else 0.0)
        all_ranks_here = True   # the summary is collective: written only where every rank ends alike
        try:
            with StopRequests() as stops:
                while self.state.time < run.end_time * (1 - 1e-12):
                    dt = next_time_step(model, self.state, min(next_output, next_checkpoint, run.end_time))
                    displacing = self.state.next_id > self.state.fresh_from   # (injected in the last step)
                    self.advance(dt)   # on a NumericalError self.state stays the state the step started from
                    watch = watch_flow(model, self.state, dt, watch, displacing)
                    time = self.state.time
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
                    progress.update(self.state.step, time, f"  particles {self.state.n_global_particles}")
                    past_limit = bool(run.wall_time_limit) and wallclock.perf_counter() - started > run.wall_time_limit
                    signal_number, past_limit = stops.agreed(self.comm, past_limit)
                    if signal_number:
                        stop = Stopped(stop_message(self.state, signal_number, output), signal_number)
                        status = f"stopped by {signal.Signals(signal_number).name}"
                    elif past_limit:
                        status = "stopped at the wall-time limit"
                    if status != "completed":
                        writers.write(self.state)
                        break
            if (every or stop) and checkpoint_time != self.state.time:   # for a later continuation
                with self.times.stage("checkpoint"):
                    checkpoint.write(self.comm, output, model.mesh, self.state)
        except NumericalError:
            status = "numerical failure"
            self.state = watch.good if model.flow is not None else self.state
            with self.times.stage("output"):   # the last good state is written first
                writers.write(self.state)
            raise
        except (CaseError, Stopped):
            raise
        except BaseException:
            # a bug, perhaps on this rank alone while the others wait in a step: no collective
            # summary then (it would hang); __main__ takes every rank down
            status, all_ranks_here = "failed: internal error", self.comm.size == 1
            raise
        finally:
            if all_ranks_here:
                total = wallclock.perf_counter() - started
                progress.update(self.state.step, self.state.time, force=True)
                seconds = {"total": total, "setup": setup_seconds, **self.times.seconds}
                io.write_summary(self.comm, output, reporting.summary(model, self.state, status, seconds))
        if stop is not None:
            raise stop


def run_from_arguments(comm, arguments) -> None:
    """Collective. Everything ``python -m pmpm`` does after parsing the command line."""
    case = load_case(case_path(arguments.case), arguments.set)
    output = Path(arguments.output) if arguments.output else case.folder / "output"
    checks.before_building(comm, case)
    if not arguments.check and comm.rank == 0 and has_walls(case) and not jit.cache_is_current():
        print0(comm, "pmpm: compiling the contact kernels first (once after installing or updating pmpm; numba "
                     "keeps them for later runs): the set-up and the first steps take a while longer")
    restart = checkpoint.read(comm, Path(arguments.restart)) if arguments.restart else None
    start = wallclock.perf_counter()
    mesh = build_mesh(comm, case)
    check_boundaries(case, mesh)
    simulation = Simulation(comm, case, mesh, quiet=arguments.quiet, case_particles=restart is None)
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
