"""Dense-suspension cases shared by tests/test_suspensions.py and bench/suspensions.py: a fixed
random packed bed in a column (Ergun), and a liquid-fluidized bed resting on its inlet (Wen & Yu,
Richardson & Zaki)."""
from __future__ import annotations

import time as wallclock
from dataclasses import replace
from pathlib import Path

import numpy as np
from mpi4py import MPI

from pmpm.case import load_case
from pmpm.injection import NewParticles
from pmpm.mesh import Mesh
from pmpm.packing import random_packing, solid_fraction
from pmpm.particles import FIXED, FREE
from pmpm.simulation import Simulation, add_particles

COLUMN = """
[run]
end_time = 100.0
dt = {dt}
gravity = {gravity}
[mesh]
box = {{ lower = [0, 0, 0], upper = [{width}, {width}, {height}], cells = [{n}, {n}, {m}] }}
[fluid]
density = {rho_f}
viscosity = {mu}
[boundary.zmin]
type = "inlet"
velocity = [0.0, 0.0, {speed}]
[boundary.zmax]
type = "outlet"
particles = "wall"
{sides}
[coupling]
volume_fraction = "{rule}"
forcing_passes = {passes}
{coupling}
{collisions}
"""
SIDES = "".join(f'[boundary.{b}]\ntype = "symmetry"\n' for b in ("xmin", "xmax", "ymin", "ymax"))


def column(comm, folder: Path, width: float, height: float, cells: tuple[int, int], dt: float, speed: float,
           density: float, viscosity: float, rule: str = "subcell", passes: int = 1, gravity=(0.0, 0.0, 0.0),
           coupling: dict | None = None, collisions: str = "") -> Simulation:
    """Collective. A square column ``width`` × ``width`` × ``height`` (m), ``cells`` = (across, up),
    symmetry sides, a uniform inlet of ``speed`` (m/s) at the bottom and an outlet on top (a screen:
    particles meet it as a wall), no particles yet; the flow starts uniform at the inlet's speed.
    ``coupling``: more [coupling] keys."""
    extra = "".join(f"{key} = {value!r}\n".replace("'", '"') for key, value in (coupling or {}).items())
    text = COLUMN.format(dt=dt, gravity=list(gravity), width=width, height=height, n=cells[0], m=cells[1],
                         rho_f=density, mu=viscosity, speed=speed, sides=SIDES, rule=rule, passes=passes,
                         coupling=extra, collisions=collisions)
    path = folder / f"column_{comm.size}_{MPI.COMM_WORLD.rank}.toml"   # ranks on COMM_SELF write their own
    path.write_text(text)
    case = load_case(path, [])
    mesh = Mesh.from_box(comm, case.box.lower, case.box.upper, case.box.cells, case.mesh.cell_type)
    sim = Simulation(comm, case, mesh, quiet=True)
    flow, state = sim.flow, sim.fluid_state
    state.u[:, 2] = speed
    state.flux[:flow.n_interior] = speed * flow.S[:, 2]
    state.flux[flow.n_interior:] = speed * flow.S_b[:, 2]
    return sim


def filtered(coupling: dict | None, diameter: float) -> dict:
    """``coupling`` with the drag correction's default filter (3 diameters) said explicitly: the
    case cannot know it, its particles are added after it is built."""
    coupling = dict(coupling or {})
    if coupling.get("drag_correction", "off") != "off":
        coupling.setdefault("correction_filter", 3.0 * diameter)
    return coupling


def with_particles(sim: Simulation, x: np.ndarray, radius: float, density: float, motion: int) -> Simulation:
    """Collective. ``sim`` with spheres at ``x`` (n, 3), at rest."""
    n = len(x)
    new = NewParticles(x, np.zeros((n, 3)), np.zeros((n, 3)), np.full(n, radius), np.full(n, density),
                       np.full(n, motion, np.int8))
    state = add_particles(sim.model, sim.state, new)
    sim.state = replace(state, fresh_from=state.next_id)    # present from the start: no displaced volume
    return sim


def ergun_pressure_gradient(mesh, fluid, volume_fraction, z_low: float, z_high: float, comm) -> float:
    """Collective. −dp/dz (Pa/m) between the heights ``z_low`` and ``z_high``: the least-squares slope of
    the fluid-weighted mean pressure of each layer of cells whose centres lie between them."""
    owned = slice(0, mesh.n_owned_cells)
    z = mesh.cell_center[owned, 2]
    weight = mesh.cell_volume[owned] * (1.0 - volume_fraction[owned])
    inside = (z > z_low) & (z < z_high)
    heights = np.round(z, 9)
    levels = np.unique(np.concatenate(comm.allgather(np.unique(heights[inside]))))
    index = np.searchsorted(levels, heights[inside])
    sums = np.zeros((2, len(levels)))
    sums[0] = np.bincount(index, weight[inside] * fluid.p[owned][inside], minlength=len(levels))
    sums[1] = np.bincount(index, weight[inside], minlength=len(levels))
    comm.Allreduce(MPI.IN_PLACE, sums, op=MPI.SUM)
    slope = np.polyfit(levels, sums[0] / sums[1], 1)[0]
    return -float(slope)


def bed_cfl(cells_per_diameter: int, reynolds: float) -> float:
    """The CFL number (on the mean interstitial speed) at which the packed bed runs: explicit
    convection blew up at 0.3 at Re 100 (4 cells per diameter) and at Re 10 (6), where the pores
    are resolved well enough to carry several times the mean speed."""
    return 0.3 if reynolds < 100 and cells_per_diameter < 6 else 0.15


def packed_bed(comm, folder: Path, cells_per_diameter: int, reynolds: float, diameter: float = 0.003,
               width: float = 4.0, bed: float = 8.0, margin: float = 1.5, porosity_section: float = 2.0,
               count: int | None = None, seed: int = 1, rule: str = "subcell", cfl: float | None = None,
               diffusion_number: float = 0.4, flow_times: float = 3.0, min_steps: int = 40, max_steps: int = 100000,
               coupling: dict | None = None, density: float = 1000.0, viscosity: float = 1e-3,
               forcing: str = "penalty", passes: int = 1) -> dict:
    """Collective. A fixed random packing of spheres (``pmpm.packing.random_packing``, mirror sides)
    ``bed`` diameters tall in a column ``width`` diameters wide with symmetry sides, ``margin``
    diameters of empty column below (the inlet) and above (the outlet); a stream at the particle
    Reynolds number ``reynolds`` = ρ U d/μ (U superficial). The pressure gradient is measured over
    the bed less ``porosity_section`` diameters at each end, the voidage ε there exactly (on a fine
    lattice). The step is the smaller of ``cfl`` h/(U/ε) (default ``bed_cfl``) and
    ``diffusion_number`` h²/ν; the run lasts ``flow_times`` passages of the bed at the interstitial
    speed U/ε, at least ``min_steps`` and at most ``max_steps`` steps.

    Returns a dict: reynolds, porosity, gradient (−dp/dz, Pa/m), its history per step, steps,
    cells, particles, seconds (wall, this run's steps)."""
    d = diameter
    h = d / cells_per_diameter
    n_across, n_up = int(round(width * cells_per_diameter)), int(round((bed + 2 * margin) * cells_per_diameter))
    w, total = n_across * h, n_up * h
    lower, upper = np.array([0.0, 0.0, margin * d]), np.array([w, w, (margin + bed) * d])
    count = count if count is not None else int(round(0.72 * w * w * bed * d / (np.pi / 6 * d ** 3)))
    x = comm.bcast(random_packing(count, lower, upper, d / 2, mirrors=(True, True, False), seed=seed)
                   if comm.rank == 0 else None)
    x[:, :2] = np.clip(x[:, :2], 1e-6 * d, w - 1e-6 * d)     # centres inside the domain
    z_low, z_high = (margin + porosity_section) * d, (margin + bed - porosity_section) * d
    porosity = 1.0 - comm.bcast(solid_fraction(x, d / 2, [0, 0, z_low], [w, w, z_high]) if comm.rank == 0 else None)
    nu = viscosity / density
    speed = reynolds * nu / d
    cfl = bed_cfl(cells_per_diameter, reynolds) if cfl is None else cfl
    dt = min(cfl * h * porosity / speed, diffusion_number * h * h / nu)
    sim = column(comm, folder, w, total, (n_across, n_up), dt, speed, density, viscosity, rule=rule, passes=passes,
                 coupling={"forcing": forcing, **filtered(coupling, d)})
    with_particles(sim, x, d / 2, 2500.0, FIXED)
    steps = min(max_steps, max(min_steps, int(np.ceil(flow_times * bed * d / (speed / porosity) / dt))))
    history = np.empty(steps)
    start = wallclock.perf_counter()
    for i in range(steps):
        sim.advance(dt)
        history[i] = ergun_pressure_gradient(sim.mesh, sim.fluid_state, sim.state.volume_fraction, z_low, z_high,
                                             comm)
    seconds = wallclock.perf_counter() - start
    return dict(reynolds=reynolds, porosity=porosity, gradient=float(history[-max(1, steps // 5):].mean()),
                history=history, steps=steps, cells=sim.mesh.n_global_cells, particles=count, seconds=seconds,
                speed=speed, diameter=d, density=density, viscosity=viscosity, dt=dt)


COLLISIONS = "[collisions]\nrestitution = 0.9\nfriction = 0.1\n"


def fluidized_bed(comm, folder: Path, speed: float, cells_per_diameter: int = 3, diameter: float = 0.003,
                  particle_density: float = 2500.0, width: float = 4.0, packed: float = 6.0, height: float = 24.0,
                  dt: float = 1e-3, duration: float = 2.0, average: float = 1.0, seed: int = 1,
                  coupling: dict | None = None, density: float = 1000.0, viscosity: float = 1e-3) -> dict:
    """Collective. A liquid-fluidized bed: free spheres (glass in water by default) packed at random
    ``packed`` diameters deep on the inlet of a column ``width`` diameters square (symmetry sides,
    which particles meet as walls) and ``height`` diameters tall, fluidized by a uniform inlet ``speed`` (m/s), run
    ``duration`` seconds; the bed's voidage from the particles' mean height z̄ (a uniform bed from the
    inlet up to H = 2 z̄ holds N V_p in A H), averaged over the last ``average`` seconds.

    Returns a dict: speed, voidage (ε over the averaging window), packed_voidage (at the start),
    height (m, H averaged), packed_height, lowest (the lowest centre over the run, m), particles,
    cells, steps, seconds (wall, the steps), history (t, H) per step. Raises ValueError if every
    particle has left the domain (a run that blew up)."""
    d = diameter
    h = d / cells_per_diameter
    n_across, n_up = int(round(width * cells_per_diameter)), int(round(height * cells_per_diameter))
    w, total = n_across * h, n_up * h
    count = int(0.45 * w * w * packed * d / (np.pi / 6 * d ** 3))
    # particles meet symmetry planes as walls: packed clear of the sides
    x = comm.bcast(random_packing(count, [0, 0, 0], [w, w, packed * d], d / 2, seed=seed) if comm.rank == 0 else None)
    sim = column(comm, folder, w, total, (n_across, n_up), dt, speed, density, viscosity, passes=3,
                 gravity=(0.0, 0.0, -9.81), coupling=filtered(coupling, d), collisions=COLLISIONS)
    with_particles(sim, x, d / 2, particle_density, FREE)
    solid = count * np.pi / 6 * d ** 3 / (w * w)           # the bed's height if it were solid (m)
    steps = int(round(duration / dt))
    history = np.empty((steps, 2))
    lowest = float(x[:, 2].min())
    start = wallclock.perf_counter()
    for i in range(steps):
        sim.advance(dt)
        z = sim.state.particles.x[:, 2]
        if len(z) == 0:
            raise ValueError(f"every particle left the domain by t = {sim.state.time:g} s")
        history[i] = sim.state.time, 2.0 * z.mean()
        lowest = min(lowest, float(z.min()))
    seconds = wallclock.perf_counter() - start
    window = history[:, 0] > duration - average
    bed = float(history[window, 1].mean())
    return dict(speed=speed, voidage=1.0 - solid / bed, packed_voidage=1.0 - solid / (2.0 * x[:, 2].mean()),
                height=bed, packed_height=2.0 * float(x[:, 2].mean()), lowest=lowest, particles=count,
                remaining=len(sim.state.particles), cells=sim.mesh.n_global_cells, steps=steps, seconds=seconds,
                history=history, diameter=d)
