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
from .injection import build_injectors, initial_particles
from .mesh import Mesh
from .parallel import agree, print0


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
