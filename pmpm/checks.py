"""Checks before a run: what a case asks of the solvers, the mesh, this machine and its disk.

Each check refuses what cannot run — a ``CaseError`` on every rank, so exit status 2 with one line
(README) — and warns on what is only suspicious. All of them run under ``--check`` as well:

- before the mesh is built (``before_building``): the PETSc options of pmpm's solvers, and the
  memory a box mesh will take against what this machine has;
- once the simulation is set up (``before_running``): the fluxes the boundaries impose (an inlet
  into a closed box, a wall moving through itself), particles and injections against the
  domain, a restart's end time, and what the run will write against the free disk.
"""
from __future__ import annotations

import math
import os
import re
import shutil
from pathlib import Path

import numpy as np
from mpi4py import MPI

from .case import Case, Section, format_value, suggest
from .errors import CaseError
from .injection import Injector
from .io import output_folder_problem
from .parallel import agree, warn

SOLVER_PREFIXES = ("pressure_", "momentum_")  # the options prefixes of pmpm's KSPs (pmpm.pressure)
# Peak resident memory per cell (bytes), measured on 1 rank over a few steps of a box (125,000
# hexahedra, 131,712 tetrahedra; bench/flow.py measures 2011 B per hexahedron at 1e6), with and
# without a flow; and what one rank takes before any cell (Python, PETSc, numpy).
BYTES_PER_CELL = {("hex", True): 2300, ("hex", False): 1400, ("tet", True): 1800, ("tet", False): 900}
BYTES_PER_RANK = 120 * 2 ** 20
# DMPlex points (cells, faces, edges, vertices) per cell: PETSc numbers them with its integer type
POINTS_PER_CELL = {"hex": 8, "tet": 4.5}
# Volume fluxes through boundaries, relative to speed × area: a net flux that refuses a case (and
# that warns); the part of a wall's motion through its faces that refuses it (and that warns). The
# faces of a curved wall are flat: a rotation about the wall's own axis crosses them by ~1/N of its
# speed with N faces around (a few %), a flapping or misplaced rotation by tens of %.
FLUX_REFUSED, FLUX_WARNED = 1e-3, 1e-9
WALL_NORMAL_REFUSED, WALL_NORMAL_WARNED = 0.1, 1e-3
STEPS_WARNED = 1e9


def before_building(comm, case: Case) -> None:
    """Collective. Refuse PETSc options the solvers cannot take and a box this machine cannot hold."""
    check_petsc_options(comm)
    check_memory(comm, case)


def before_running(comm, model, state, output: Path, restart: str | None) -> str:
    """Collective. Refuse (or warn about) what the built ``model`` (``pmpm.simulation.Model``) cannot
    run or write from its first ``state`` (``pmpm.state.RunState``; a checkpoint's on a restart).

    Returns the line that says what the run will write (outputs, estimated sizes, free disk).
    """
    case, mesh = model.case, model.mesh
    check_boundary_settings(comm, case)
    check_boundary_fluxes(comm, case, mesh)
    try:   # (where ranks own particles, each checks its own)
        check_particles_fit(case, mesh, state.particles)
        error = None
    except CaseError as exc:
        error = exc
    agree(comm, error)
    check_injections(comm, model, state)
    if restart is not None and state.time >= case.run.end_time * (1 - 1e-12):
        raise CaseError(f"--restart {restart}: the checkpoint is at t = {state.time:g} s, at or after "
                        f"[run] end_time = {case.run.end_time:g} s: nothing to run; raise end_time "
                        f"(e.g. --set run.end_time={2 * state.time:g})")
    steps = (case.run.end_time - state.time) / case.run.dt
    if steps > STEPS_WARNED and comm.rank == 0:
        warn(comm, f"[run] end_time = {case.run.end_time:g} s with dt = {case.run.dt:g} s is {steps:.3g} steps: "
                   f"even at a millisecond a step that is {steps * 1e-3 / 3.156e7:.3g} years; check dt and "
                   "end_time, or stop cleanly with [run] wall_time_limit")
    error = None
    if comm.rank == 0:
        problem = output_folder_problem(output.resolve())
        error = CaseError(f"output folder {output.resolve()}: {problem}") if problem else None
    agree(comm, error)
    return check_disk(comm, model, state, output.resolve())


# -- PETSc options ------------------------------------------------------------------------------
def check_petsc_options(comm) -> None:
    """Collective. Each solver's PETSc options, tried on a throwaway KSP; a type PETSc does not know
    or a value it cannot take is refused, naming the option. Solver options under no prefix that
    pmpm reads (``-ksp_monitor``, ``-presure_pc_type``) are ignored by PETSc: warn."""
    from petsc4py import PETSc

    error = None
    try:
        for prefix in SOLVER_PREFIXES:
            _try_solver_options(PETSc, prefix)
    except CaseError as exc:
        error = exc
    agree(comm, error)
    if comm.rank == 0:
        for name in sorted(PETSc.Options().getAll()):
            if not name.startswith(SOLVER_PREFIXES) and re.search(r"(^|_)(ksp|pc|mg|mat)_", name):
                warn(comm, f"PETSc option -{name}: no pmpm solver reads it; pmpm's solvers read options under "
                           f"{' and '.join('-' + p for p in SOLVER_PREFIXES)} (e.g. -pressure_ksp_monitor)")


def _try_solver_options(PETSc, prefix: str) -> None:
    options = PETSc.Options()
    for suffix, make, types in (("ksp_type", PETSc.KSP, PETSc.KSP.Type), ("pc_type", PETSc.PC, PETSc.PC.Type)):
        name = prefix + suffix
        if not options.hasName(name):
            continue
        value = options.getString(name, "")
        trial = make().create(comm=PETSc.COMM_SELF)
        try:
            trial.setType(value)
        except PETSc.Error as exc:
            known = sorted(getattr(types, t) for t in dir(types) if t.isupper())
            raise CaseError(f"-{name} {value}: {_petsc_reason(exc)}{suggest(value, known)}") from None
        finally:
            trial.destroy()
    ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
    matrix = PETSc.Mat().createAIJ(size=(1, 1), nnz=1, comm=PETSc.COMM_SELF)
    try:
        matrix.setValue(0, 0, 1.0)
        matrix.assemble()
        ksp.setOptionsPrefix(prefix)
        ksp.setOperators(matrix)
        ksp.setFromOptions()
    except PETSc.Error as exc:
        given = " ".join(f"-{k} {v}".strip() for k, v in sorted(options.getAll().items()) if k.startswith(prefix))
        raise CaseError(f"PETSc options {given}: {_petsc_reason(exc)}") from None
    finally:
        ksp.destroy()
        matrix.destroy()


def _petsc_reason(error) -> str:
    """PETSc's own last line of an error (``Unable to find requested KSP type nonsense``)."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return re.sub(r"^\[\d+\]\s*", "", lines[-1]) if lines else f"PETSc error {getattr(error, 'ierr', '')}"


# -- memory -------------------------------------------------------------------------------------
def check_memory(comm, case: Case) -> None:
    """Collective. A box mesh's cells against PETSc's index range and the memory of this machine,
    estimated before anything is built: refuse what cannot fit, warn above the memory free now."""
    if case.box is None:   # a mesh file is read first; its size is known only then
        return
    cell_type = case.mesh.cell_type
    cells = math.prod(case.box.cells) * (6 if cell_type == "tet" else 1)
    where = f"{case.path.name}: [mesh.box] cells = {format_value(case.box.cells)}"
    shape = "tetrahedra" if cell_type == "tet" else "hexahedra"
    per_cell = BYTES_PER_CELL[(cell_type, case.fluid is not None)]
    node = comm.Split_type(MPI.COMM_TYPE_SHARED)
    ranks_here = node.size
    node.Free()
    need = cells * per_cell * ranks_here / comm.size + ranks_here * BYTES_PER_RANK
    total, available = machine_memory()
    error = None
    if total is not None and need > total:
        error = CaseError(f"{where}: {cells:.3g} {shape} need ≈ {size_text(need)} of memory on this machine "
                          f"({ranks_here} rank(s) here, ≈ {per_cell} B per cell{' with the flow' if case.fluid else ''}), "
                          f"which has {size_text(total)} ({size_text(available or 0)} free); use fewer cells or more machines")
    agree(comm, error)
    from petsc4py import PETSc
    index_bits = 8 * np.dtype(PETSc.IntType).itemsize
    most = int((2 ** (index_bits - 1) - 1) / POINTS_PER_CELL[cell_type])
    if cells > most:
        raise CaseError(f"{where}: {cells:.3g} {shape}, more than the {most:.3g} that PETSc's {index_bits}-bit "
                        "indices can number; use fewer cells")
    if available is not None and need > available and comm.rank == 0:
        warn(comm, f"[mesh.box] cells = {format_value(case.box.cells)}: {cells:.3g} {shape} need ≈ {size_text(need)} "
                   f"of memory on this machine, more than the {size_text(available)} free now")


def machine_memory() -> tuple[int | None, int | None]:
    """(total, available) bytes of memory for this process: the machine's, within a cgroup limit."""
    total = available = None
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    available = int(line.split()[1]) * 1024
    except (OSError, ValueError):
        pass
    for limit_file in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            limit = int(Path(limit_file).read_text().split()[0])
        except (OSError, ValueError, IndexError):   # absent, or "max"
            continue
        total = limit if total is None else min(total, limit)
        available = None if available is None else min(available, limit)
    return total, available


def size_text(n_bytes: float) -> str:
    """``1.2 GB``: bytes in decimal units."""
    for unit in ("B", "kB", "MB", "GB", "TB", "PB", "EB"):
        if abs(n_bytes) < 1000 or unit == "EB":
            return f"{n_bytes:.3g} {unit}"
        n_bytes /= 1000
    return ""


# -- boundaries ---------------------------------------------------------------------------------
def check_boundary_settings(comm, case: Case) -> None:
    """Warn about [boundary.<name>] keys that the boundary's type ignores."""
    if comm.rank != 0:
        return
    used = {"wall": ("velocity", "angular_velocity", "center", "motion", "restitution", "friction",
                     "rolling_friction"),
            "inlet": ("velocity",), "outlet": ("pressure",), "symmetry": ()}
    defaults = {"velocity": (0.0, 0.0, 0.0), "angular_velocity": (0.0, 0.0, 0.0), "pressure": 0.0}
    for name, section in case.boundaries.items():
        ignored = [key for key, default in defaults.items()
                   if key not in used[section.type] and getattr(section, key) != default]
        if ignored:
            warn(comm, f"[boundary.{name}] {', '.join(ignored)}: ignored on a boundary of type \"{section.type}\"")


def check_boundary_fluxes(comm, case: Case, mesh) -> None:
    """Collective. The volume fluxes the boundaries impose on an incompressible flow.

    A wall's surface can only slide along itself: a wall velocity that carries fluid through the
    wall (net, or in and out over its parts as a flapping plate would) is refused; a small normal
    part, as the facets of a coarse curved wall give a rotation, is warned about. Without an
    outlet, what the inlets (and walls) bring in must leave through them too: a net flux is
    refused, naming the boundaries that carry it. An inlet that carries nothing is warned about.
    """
    name = case.path.name
    names = list(mesh.boundary_names)
    faces = np.flatnonzero(mesh.face_boundary >= 0)
    which = mesh.face_boundary[faces]
    area_vec, centre = mesh.face_area_vec[faces], mesh.face_center[faces]
    n = len(names)
    # per boundary: net flux Σ u·S, Σ |u·S|, and Σ |u| |S| (what the speed would carry if normal)
    sums = np.zeros((3, n))
    for index, boundary in enumerate(names):
        section = case.boundaries.get(boundary)
        if section is None or section.type not in ("wall", "inlet") or (section.type == "wall" and section.motion == "rigid"):
            continue
        here = which == index
        velocity = np.asarray(section.velocity, float)
        if section.type == "wall":   # as pmpm.fluid: V + Ω × (x_f − centre) at each face centre
            velocity = velocity + np.cross(np.asarray(section.angular_velocity, float),
                                           centre[here] - np.asarray(section.center, float))
        u = np.broadcast_to(velocity, (int(here.sum()), 3))
        normal_flux = np.einsum("ij,ij->i", u, area_vec[here])
        sums[:, index] = (normal_flux.sum(), np.abs(normal_flux).sum(),
                          np.sum(np.linalg.norm(u, axis=1) * np.linalg.norm(area_vec[here], axis=1)))
    comm.Allreduce(MPI.IN_PLACE, sums, op=MPI.SUM)
    flux, through, scale = sums
    kinds = {b: (case.boundaries[b].type if b in case.boundaries else "wall") for b in names}
    net_part = np.divide(np.abs(flux), scale, out=np.zeros(n), where=scale > 0)
    normal_part = np.divide(through, scale, out=np.zeros(n), where=scale > 0)

    for index, boundary in enumerate(names):
        section = case.boundaries.get(boundary)
        if kinds[boundary] == "wall" and case.fluid is None:
            # no flow to break; the collisions drop the normal part (pmpm.collisions)
            if normal_part[index] > WALL_NORMAL_WARNED and comm.rank == 0:
                warn(comm, f"[boundary.{boundary}] the wall's velocity has a part normal to the wall, which the "
                           "collisions ignore: a wall's surface slides along itself")
        elif kinds[boundary] == "wall":
            if net_part[index] > FLUX_REFUSED or normal_part[index] > WALL_NORMAL_REFUSED:
                raise CaseError(f"{name}: [boundary.{boundary}] velocity = {format_value(section.velocity)}, "
                                f"angular_velocity = {format_value(section.angular_velocity)}, center = "
                                f"{format_value(section.center)}: the wall's surface would carry fluid through the "
                                f"wall ({through[index]:.3g} m³/s across its faces, net {flux[index]:.3g} m³/s); a wall's "
                                "surface can only slide along itself: give a motion along the wall, or make the "
                                "boundary an inlet")
            if normal_part[index] > WALL_NORMAL_WARNED and comm.rank == 0:
                warn(comm, f"[boundary.{boundary}] the wall's velocity carries {through[index]:.3g} m³/s through its "
                           f"faces, {100 * normal_part[index]:.2g} % of its speed × area (a coarsely faceted curved "
                           "wall, or a rotation centre or axis off the wall's own?)")
        elif kinds[boundary] == "inlet" and net_part[index] <= FLUX_WARNED and comm.rank == 0:
            warn(comm, f"[boundary.{boundary}] inlet velocity = {format_value(section.velocity)} carries no flow through "
                       "the boundary (zero, or along it): a moving surface is a wall with a velocity")
    if case.fluid is None or any(kind == "outlet" for kind in kinds.values()):
        return
    net, gross = float(flux.sum()), float(scale.sum())
    if gross == 0 or abs(net) <= FLUX_WARNED * gross:
        return
    listed = ", ".join(f"{b} ({kinds[b]}) {-flux[i]:+.3g} m³/s" for i, b in enumerate(names) if scale[i] > 0)
    if abs(net) > FLUX_REFUSED * gross:
        raise CaseError(f"{name}: the boundaries bring a net {-net:+.3g} m³/s into a domain with no outlet ({listed}; "
                        "+ is into the domain): an incompressible flow cannot take it; add an outlet "
                        "([boundary.<name>] type = \"outlet\"), or let as much out as comes in")
    if comm.rank == 0:
        warn(comm, f"the boundaries bring a net {-net:+.3g} m³/s into a domain with no outlet ({listed}): the flow "
                   "cannot be divergence-free to better than that")


# -- particles and injections -------------------------------------------------------------------
def domain_extent_text(mesh) -> str:
    extent = mesh.upper - mesh.lower
    return " × ".join(f"{e:g}" for e in extent) + " m"


def check_particles_fit(case: Case, mesh, particles) -> None:
    """Refuse a sphere too large for the domain's bounding box (with or without [collisions])."""
    smallest = float(np.min(mesh.upper - mesh.lower))
    too_big = np.flatnonzero(2 * particles.radius > smallest)
    if len(too_big):
        i = too_big[0]
        raise CaseError(f"{case.path.name}: particle {int(particles.id[i])}: radius {particles.radius[i]:g} m: a sphere "
                        f"of diameter {2 * particles.radius[i]:g} m does not fit in the domain "
                        f"({domain_extent_text(mesh)})")


def check_injections(comm, model, state, samples: int = 64) -> None:
    """Collective. Each [[injection]] against the domain: a sphere that cannot fit, release points
    that all lie outside (nothing would ever be released) are refused; some outside, or no release
    before end_time, warned about. Sampled: the first release and up to ``samples`` in all."""
    case, mesh = model.case, model.mesh
    name, end = case.path.name, case.run.end_time
    smallest = float(np.min(mesh.upper - mesh.lower))
    if model.injectors and model.flow is not None and model.flow.pressure.pure_neumann and comm.rank == 0:
        warn(comm, "[[injection]] into a fluid with no outlet: the fluid the new particles displace has nowhere to go "
                   "(incompressible, in a closed domain), so their volume is spread over the whole domain instead "
                   "of leaving; add an outlet ([boundary.<name>] type = \"outlet\") for the paper's mass balance")
    for injector, first in zip(model.injectors, state.releases):
        s, i = injector.section, injector.index
        where = f"{name}: [[injection]] #{i} ({s.kind})"
        if 2 * s.radius > smallest:
            raise CaseError(f"{where}: radius = {s.radius:g} m: a sphere of diameter {2 * s.radius:g} m does not fit "
                            f"in the domain ({domain_extent_text(mesh)})")
        last_time = min(s.stop, end)
        if injector.release_time(first) > last_time * (1 + 1e-12):
            if comm.rank == 0:
                warn(comm, f"[[injection]] #{i}: no release before end_time = {end:g} s (start = {s.start:g} s)")
            continue
        last = max(first, int(math.floor((last_time - s.start) / s.interval + 1e-9)))
        releases = np.unique(np.linspace(first, last, min(samples, last - first + 1)).round().astype(np.int64))
        # a few particles of each sampled release tell where it lands (count may be large)
        few = Injector(Section({**s.values, "count": min(s.count, 8)}), injector.index, injector.seed)
        points = np.concatenate([few.release(int(k)).x for k in releases])
        inside = mesh.inside_domain(points).reshape(len(releases), -1)
        if not inside.any():
            first_point = points[0]
            raise CaseError(f"{where}: the release point{'s' if len(releases) > 1 or inside.shape[1] > 1 else ''} "
                            f"(first: [{', '.join(f'{v:g}' for v in first_point)}] at t = {injector.release_time(first):g} s) "
                            f"lie outside the domain ({', '.join(f'{l:g}..{u:g}' for l, u in zip(mesh.lower, mesh.upper))} m): "
                            "nothing would be released")
        if not inside.all() and comm.rank == 0:
            warn(comm, f"[[injection]] #{i}: {100 * (1 - inside.mean()):.0f} % of the release points sampled lie outside "
                       "the domain; releases there are skipped")


# -- what the run writes ------------------------------------------------------------------------
def check_disk(comm, model, state, folder: Path) -> str:
    """Collective. Estimate what the run will write; refuse more than the free disk holds.

    Returns one line for the run's header: outputs, particles, estimated sizes, free disk.
    """
    case, mesh = model.case, model.mesh
    run = case.run
    start = state.time
    steps = math.ceil((run.end_time - start) / run.dt - 1e-9)
    # the state at the start, then at most one output a step
    n_outputs = 1 + max(0, min(steps, math.ceil((run.end_time - start) / run.output_every - 1e-9)))
    cells = mesh.n_global_cells
    vertices = int(comm.allreduce(int(np.count_nonzero(mesh.vertex_owned))))
    corners = mesh.cell_vertices.shape[1]
    with_fluid = model.flow is not None
    n_now = state.n_global_particles
    injected = 0.0
    for injector, next_release in zip(model.injectors, state.releases):
        s = injector.section
        last_time = min(s.stop, run.end_time)
        if s.start <= last_time:
            releases = math.floor((last_time - s.start) / s.interval + 1e-9) + 1 - next_release
            injected += max(0, releases) * s.count
    mean_particles = n_now + injected / 2      # released over the run: half of them on average
    columns = 13 + (6 if with_fluid else 0)
    csv = n_outputs * mean_particles * columns * 17.0                            # "%.12g," ≈ 17 characters
    mesh_bytes = vertices * 24 + cells * (8 * corners + 24 + 8)
    per_output = (40 * cells if with_fluid else 0) + 96 * mean_particles + 8192   # fields, particles, HDF5 groups
    fields = mesh_bytes + n_outputs * per_output + n_outputs * 2000               # + the XDMF index
    checkpoint = 0.0
    if run.checkpoint_every:
        faces = 3 * cells if mesh.cell_type == "hex" else 2 * cells
        # the previous checkpoint stays whole while the next is written
        checkpoint = 2 * ((32 * cells + 40 * faces if with_fluid else 0) + 200 * (n_now + injected) + 8192)
    total = csv + fields + checkpoint
    free = None
    if comm.rank == 0:
        existing = folder
        while not existing.exists() and existing != existing.parent:
            existing = existing.parent
        try:
            free = shutil.disk_usage(existing).free
        except OSError:
            free = None
    free = comm.bcast(free, root=0)
    if free is not None and total > free:
        raise CaseError(f"{case.path.name}: [run] output_every = {run.output_every:g} s: {n_outputs:.3g} outputs would "
                        f"write ≈ {size_text(total)} into {folder}, which has {size_text(free)} free; raise output_every, "
                        "shorten end_time, or write elsewhere (--output)")
    particles = f"{n_now} particle{'' if n_now == 1 else 's'}" + (f" + {injected:.3g} injected" if injected else "")
    return (f"  writes:    {n_outputs:.6g} outputs ({particles}) into {folder}: ≈ {size_text(total)} "
            f"(fields.h5 {size_text(fields)}, particles.csv {size_text(csv)}"
            + (f", checkpoints {size_text(checkpoint)}" if checkpoint else "") + ")"
            + (f"; {size_text(free)} free" if free is not None else ""))
