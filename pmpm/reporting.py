"""What a run tells its user: the description before it starts, progress lines, warnings on the
way, and summary.json at the end (wall seconds per stage, conservation diagnostics)."""
from __future__ import annotations

import math
import resource
import time as wallclock
from contextlib import contextmanager

import numpy as np
from mpi4py import MPI

from .ownership import gather
from .parallel import allreduce_sum, print0, warn


class StageTimes:
    """Wall seconds per stage of the time step, summed over the run (this rank's clock).

    Stages do not nest: ``with times.stage("flow"):`` around the flow's own calls only, so the
    seconds of the stages add up to the step's."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str):
        start = wallclock.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + wallclock.perf_counter() - start


PACE_STEPS = 3   # the fewest steps a progress line's ETA is taken from (fewer: the last pace, or "?")


class Progress:
    """Compact progress lines on rank 0: step, simulated time, wall time, ETA, every few seconds.

    The ETA is the simulated time left at the median pace (wall seconds per simulated second) of
    the steps since the last line (at least ``PACE_STEPS``; "?" until there have been as many), so
    that a few slow steps do not set it: the first ones of a run, which compile or load the
    contact kernels (tens of seconds on a first run), and those that write outputs."""

    def __init__(self, comm, end_time: float, quiet: bool, every_seconds: float = 5.0, start_time: float = 0.0):
        self.comm, self.end_time, self.quiet, self.every = comm, end_time, quiet, every_seconds
        self.start = self.last = self.last_step = wallclock.perf_counter()
        self.last_time = start_time
        self.paces: list[float] = []   # wall s per simulated s of each step since the last line
        self.pace = math.nan            # ... their median at the last line

    def update(self, step: int, time: float, extra: str = "", force: bool = False):
        """After each step: its pace noted; a line printed if ``every_seconds`` have passed (or ``force``)."""
        if self.quiet:
            return
        now = wallclock.perf_counter()
        if time > self.last_time:
            self.paces.append((now - self.last_step) / (time - self.last_time))
        self.last_step, self.last_time = now, time
        if not force and now - self.last < self.every:
            return
        self.last = now
        if len(self.paces) >= PACE_STEPS:
            self.pace, self.paces = float(np.median(self.paces)), []
        eta = self.pace * (self.end_time - time) if time < self.end_time else 0.0
        eta_text = f"{eta:8.1f}" if math.isfinite(eta) else f"{'?':>8}"
        print0(self.comm, f"step {step:7d}  t = {time:.6g} s  ({100 * time / self.end_time:5.1f} %)  "
                          f"wall {now - self.start:8.1f} s  ETA {eta_text} s{extra}")


def describe(model, state, setup_seconds: float) -> str:
    """Collective (with a flow). What the run will do, printed before it starts."""
    case, mesh, comm = model.case, model.mesh, model.comm
    run = case.run
    steps = math.ceil(run.end_time / run.dt - 1e-9)
    return "\n".join([
        f"pmpm: case {case.path}",
        f"  models:    {', '.join(case.models()) or 'none'}",
        f"  mesh:      {mesh.describe()}",
        f"  particles: {state.n_global_particles} at start, {len(model.injectors)} injection(s)",
        f"  ranks:     {comm.size}",
        f"  time:      0 → {run.end_time:g} s, " + (f"dt = {run.dt:g} s ({steps} steps)" if not run.adaptive_cfl else
                                                   f"dt ≤ {run.dt:g} s adapted to CFL {run.adaptive_cfl:g}")
        + f", output every {run.output_every:g} s",
        *([describe_flow(model, state)] if model.flow is not None else []),
        f"  setup:     {setup_seconds:.2f} s",
    ])


def describe_flow(model, state) -> str:
    """Collective. One line on the flow, with the CFL number the boundary velocities give; warns
    when it exceeds [run] max_cfl, and when ν dt/h² is large enough to move a particle's drag."""
    case, flow, comm = model.case, model.flow, model.comm
    fluid, run = case.fluid, case.run
    cfl = flow.boundary_cfl(run.dt)
    h = float(flow.h.min(initial=np.inf))
    if cfl > run.max_cfl and not run.adaptive_cfl and comm.rank == 0:
        warn(comm, f"[run] dt = {run.dt:g} s gives a CFL number of {cfl:.2f} at the boundary velocities "
                   f"(above max_cfl = {run.max_cfl:g}); the explicit convection may go unstable")
    diffusion = comm.allreduce(fluid.viscosity / fluid.density * run.dt / h ** 2, op=MPI.MAX)
    if diffusion > 1 and (state.n_global_particles or model.injectors) and comm.rank == 0:
        warn(comm, f"[run] dt = {run.dt:g} s gives ν dt/h² = {diffusion:.3g}: above 1 the drag on particles "
                   "falls with dt, the more so the fewer cells per diameter (docs/coupling.md); a smaller dt keeps it")
    warn_outside_validation(model, state, float(np.linalg.norm(flow.u_fixed, axis=1).max(initial=0.0)))
    coupling = case.coupling
    return (f"  flow:      ρ = {fluid.density:g} kg/m³, μ = {fluid.viscosity:g} Pa s, {fluid.convection} "
            f"convection, CFL at boundary speeds {cfl:.2f}, ν dt/h² {diffusion:.3g}; coupling "
            f"{coupling.mode}, {coupling.forcing} forcing, {coupling.volume_fraction} volume fraction, "
            f"{coupling.update} update, {coupling.forcing_passes} forcing passes")


def warn_outside_validation(model, state, boundary_speed: float) -> None:
    """Collective. Warn where particles are resolved more coarsely, or may meet the flow at a higher
    Reynolds number, than the coupling was validated for (bench/drag_curve.py, docs/coupling.md):
    fewer than 3 cells per diameter; Re above 1000; Re above (d/h)², where the boundary layer, about
    d/√Re thick, is thinner than a cell and the drag comes out too high (unless the drag correction,
    which takes that excess off, is on). The relative speed is
    bounded by the boundary velocities, the particles' own and their settling speed in still fluid
    (Schiller–Naumann)."""
    from .reference import terminal_velocity

    comm, mesh, flow, fluid = model.comm, model.mesh, model.flow, model.case.fluid
    particles, injectors = state.particles, model.injectors
    if state.partition is not None:   # (at start-up: every rank looks at every particle)
        particles = gather(comm, particles)
    boundary_speed = comm.allreduce(boundary_speed, op=MPI.MAX)
    h_max = comm.allreduce(float(flow.h[:mesh.n_owned_cells].max(initial=0.0)), op=MPI.MAX)
    gravity = float(np.linalg.norm(model.case.run.gravity))
    # present particles: h of the cell holding the centre; injected ones: the coarsest cell
    cells = mesh.find_owned_cells(particles.x)
    h = np.where(cells >= 0, flow.h[np.maximum(cells, 0)], 0.0)
    if comm.size > 1:
        comm.Allreduce(MPI.IN_PLACE, h, op=MPI.MAX)
    diameter = np.concatenate([2 * particles.radius, [2 * i.section.radius for i in injectors]])
    density = np.concatenate([particles.density, [i.section.density for i in injectors]])
    own_speed = np.concatenate([np.linalg.norm(particles.v, axis=1),
                                [np.linalg.norm(i.section.velocity) for i in injectors]])
    free = np.concatenate([particles.motion == 0, np.ones(len(injectors), bool)])
    h = np.concatenate([np.where(h > 0, h, h_max), np.full(len(injectors), h_max)])
    if not len(diameter) or comm.rank:
        return
    settling = np.zeros(len(diameter))
    sinking = free & (density != fluid.density) & (gravity > 0)
    settling[sinking] = terminal_velocity(density[sinking], fluid.density, fluid.viscosity, diameter[sinking], gravity)
    reynolds = fluid.density * np.maximum.reduce([np.full(len(diameter), boundary_speed), own_speed, settling]) \
        * diameter / fluid.viscosity
    resolution = diameter / h * (1 + 1e-12)   # a diameter of 3 h is 3 cells, whatever its round-off
    if resolution.min() < 3:
        warn(comm, f"{int((resolution < 3).sum())} particle(s) span fewer than 3 cells per diameter (down to "
                   f"{resolution.min():.2g}): the coupling's drag and blockage are validated from 3 on (docs/coupling.md)")
    worst = int(np.argmax(reynolds / resolution ** 2))
    if reynolds.max() > 1000:
        warn(comm, f"particles may meet the flow at Re ≈ {reynolds.max():.3g} (boundary, particle and settling speeds): "
                   "the drag is validated up to Re 1000 (docs/coupling.md)")
    elif reynolds[worst] > resolution[worst] ** 2 and model.case.coupling.drag_correction == "off":
        warn(comm, f"particles may meet the flow at Re ≈ {reynolds[worst]:.3g} on {resolution[worst]:.2g} cells per "
                   "diameter: above Re = (d/h)² the boundary layer (≈ d/√Re) is thinner than a cell and the drag "
                   "comes out too high (docs/coupling.md: its error by Re and resolution); [coupling] "
                   "drag_correction = \"di_felice\" takes the excess off")


def warn_once(comm, message: str) -> None:
    """A warning from rank 0 of something every rank knows (not collective)."""
    if comm.rank == 0:
        warn(comm, message)


def summary(model, state, status: str, seconds: dict) -> dict:
    """Collective. The contents of summary.json."""
    owned = state.partition is not None
    count = state.n_global_particles
    return {
        "case": str(model.case.path), "status": status, "ranks": model.comm.size,
        "cells": model.mesh.n_global_cells, "particles": count, "particles_removed": state.removed,
        "particles_removed_through": dict(state.removed_through),
        **({"particles_per_rank": largest_per_rank(model.comm, state.ranks_seen)} if owned else {}),
        "steps": state.step, "simulated_time": state.time, "models": model.case.models(),
        "wall_seconds": seconds,
        "peak_memory_mb": peak_memory_mb(model.comm),
        "diagnostics": diagnostics(model, state),
    }


def peak_memory_mb(comm) -> dict:
    """Collective. The largest resident memory (MB) a rank reached so far, and the sum over ranks
    (``ru_maxrss``: the process's peak, Python, PETSc and MPI included). Each rank's peak is rounded
    before the sum, so the sum never exceeds the ranks times the largest as printed."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # kB on Linux
    peaks = [round(peak, 1) for peak in comm.allgather(own)]
    return {"largest_rank": max(peaks), "all_ranks": round(sum(peaks), 1)}


def largest_per_rank(comm, seen: dict) -> dict:
    """Collective. The most owned and ghost particles a rank held in a step of the run, and the most
    bytes a rank sent in one contact step (ghosts, shadow-copy merges, gathered contacts)."""
    keys = ("owned", "ghosts", "exchanged_bytes")
    largest = np.max(comm.allgather([seen.get(key, 0) for key in keys]), axis=0)
    return {"largest_owned": int(largest[0]), "largest_ghosts": int(largest[1]),
            "largest_bytes_sent_in_a_contact_step": int(largest[2])}


def diagnostics(model, state) -> dict:
    """Collective. Conservation checks for summary.json."""
    particles = state.particles
    sums = np.concatenate([[0.5 * float(np.sum(particles.mass * np.sum(particles.v ** 2, axis=1)))],
                           (particles.mass[:, None] * particles.v).sum(axis=0)])
    if state.partition is not None:   # each rank its own particles
        sums = allreduce_sum(model.comm, sums)
    result = {"particle_kinetic_energy": float(sums[0]), "particle_momentum": sums[1:]}
    if model.contact_settings is not None:
        result["collisions"] = dict(state.collision_totals)
    if model.injectors:
        result["injection"] = {"placed": 0, "retried": 0, "dropped": 0, **state.injection_counts}
    if state.body_forces is not None:
        result["body_forces"] = {body.name: {"force": row[:3], "torque": row[3:]}
                                 for body, row in zip(model.bodies, state.body_forces)}
    if model.flow is not None:
        flow, fluid, mesh = model.flow, state.fluid, model.mesh
        owned = slice(0, mesh.n_owned_cells)
        momentum = flow.rho * (mesh.cell_volume[owned, None] * fluid.u[owned]).sum(axis=0)
        fluxes = flow.boundary_flux(fluid)
        result.update({
            "fluid_kinetic_energy": flow.kinetic_energy(fluid),
            "fluid_momentum": allreduce_sum(model.comm, momentum),
            "max_divergence_per_second": flow.divergence_norm(fluid),
            "boundary_volume_flux": fluxes,
            "net_volume_flux": sum(fluxes.values()),
            "pressure_iterations": state.pressure_iterations,
            "final_cfl": flow.cfl(fluid, state.dt or model.case.run.dt),
        })
    return result
