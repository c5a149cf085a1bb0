"""Soak: a packed bed of a few hundred spheres held for many steps through the whole time loop
(``Simulation.advance``: forces, contacts, walls). What must not drift over a long run is printed
at ten points and compared between the start and the end: the kinetic energy (a bed at rest stays
at rest), the largest overlap between spheres and with the walls (relative to the radius), the
process's resident memory (nothing accumulates step after step), and the time per step.

    OMP_NUM_THREADS=1 .venv/bin/python bench/soak.py        # 300 spheres, 100,000 steps

The bed is poured first (spheres on a jittered lattice, 0.3 s of settling, not counted), then
held for ``--steps`` steps of 1e-4 s. No fluid (a coupled version's 0.3 s pour alone ran past 5 min).
"""
from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pmpm.case import load_case  # noqa: E402
from pmpm.simulation import Simulation, build_mesh  # noqa: E402

RADIUS, SIDE, HEIGHT, DT = 0.004, 0.06, 0.12, 1e-4

CASE = """
[run]
end_time = 1e6
dt = {dt}
gravity = [0.0, 0.0, -9.81]
[mesh]
box = {{ lower = [0.0, 0.0, 0.0], upper = [{side}, {side}, {height}], cells = [{cells}, {cells}, {cells_z}] }}
[particles]
file = "bed.txt"
[collisions]
restitution = 0.5
friction = 0.5
rolling_friction = 0.01
"""

def lattice(count: int, seed: int = 3) -> np.ndarray:
    """``count`` centres on a jittered cubic lattice (spacing 2.4 r), clear of the walls."""
    rng = np.random.default_rng(seed)
    axis = np.arange(1.3 * RADIUS, SIDE - 1.3 * RADIUS, 2.4 * RADIUS)
    levels = np.arange(1.3 * RADIUS, HEIGHT - 1.3 * RADIUS, 2.4 * RADIUS)
    z, y, x = np.meshgrid(levels, axis, axis, indexing="ij")
    centres = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    if count > len(centres):
        sys.exit(f"soak: at most {len(centres)} spheres fit the box")
    return centres[:count] + rng.uniform(-0.1, 0.1, (count, 3)) * RADIUS


def largest_overlaps(x: np.ndarray, radius: np.ndarray) -> tuple[float, float]:
    """The largest overlap between two spheres and between a sphere and the box's walls, over r."""
    gap = np.linalg.norm(x[:, None] - x[None], axis=2) - (radius[:, None] + radius[None])
    np.fill_diagonal(gap, np.inf)
    to_walls = np.column_stack([x, [SIDE, SIDE, HEIGHT] - x]).min(axis=1) - radius
    return max(0.0, -gap.min()) / RADIUS, max(0.0, -to_walls.min()) / RADIUS


def resident_mb() -> float:
    """The process's resident memory now (MB), from /proc (Linux); its peak if that is missing."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * resource.getpagesize() / 1e6
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=300)
    parser.add_argument("--steps", type=int, default=100_000)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        centres = lattice(args.particles)
        rows = np.column_stack([centres, np.full(len(centres), RADIUS), np.full(len(centres), 2500.0)])
        np.savetxt(folder / "bed.txt", rows, header="x y z radius density", comments="")
        (folder / "case.toml").write_text(CASE.format(dt=DT, side=SIDE, height=HEIGHT, cells=4, cells_z=8))
        case = load_case(folder / "case.toml", [])
        sim = Simulation(MPI.COMM_SELF, case, build_mesh(MPI.COMM_SELF, case), quiet=True)
        for _ in range(int(0.3 / DT)):   # pour
            sim.advance(DT)

        def measure() -> tuple:
            p = sim.particles
            mass = p.density * 4 / 3 * np.pi * p.radius ** 3
            energy = 0.5 * np.sum(mass * np.sum(p.v ** 2, axis=1)) + 0.5 * np.sum(
                0.4 * mass * p.radius ** 2 * np.sum(p.omega ** 2, axis=1))
            return (energy, *largest_overlaps(p.x, p.radius), resident_mb())

        print(f"soak: {args.particles} spheres (r = {RADIUS * 1e3:g} mm) poured for 0.3 s, then {args.steps} steps "
              f"of {DT:g} s, no fluid")
        print(f"{'step':>8} {'kinetic energy (J)':>19} {'overlap pairs/r':>16} {'walls/r':>9} {'RSS (MB)':>9} "
              f"{'ms/step':>8}")
        first = measure()
        print(f"{0:>8} {first[0]:>19.3e} {first[1]:>16.2e} {first[2]:>9.2e} {first[3]:>9.1f} {'':>8}")
        report_every = max(1, args.steps // 10)
        clock = time.perf_counter()
        last = first
        for step in range(1, args.steps + 1):
            sim.advance(DT)
            if step % report_every == 0:
                now = time.perf_counter()
                last = measure()
                print(f"{step:>8} {last[0]:>19.3e} {last[1]:>16.2e} {last[2]:>9.2e} {last[3]:>9.1f} "
                      f"{1e3 * (now - clock) / report_every:>8.3f}", flush=True)
                clock = now
        print(f"start → end: kinetic energy {first[0]:.3e} → {last[0]:.3e} J, largest overlap {first[1]:.2e} → "
              f"{last[1]:.2e} r (walls {first[2]:.2e} → {last[2]:.2e} r), RSS {first[3]:.1f} → {last[3]:.1f} MB")


if __name__ == "__main__":
    main()
