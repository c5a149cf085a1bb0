"""Speed against accuracy of the particle coupling: Stokes drag error against wall time over the
knobs (forcing, cells per diameter, volume-fraction rule, forcing passes, time step as the
diffusion number ν dt/h²). Writes bench/results/accuracy.csv and accuracy.png and prints the table.

    .venv/bin/python bench/accuracy.py            # about 20 minutes on one core (--settling: that part only)

The case is tests/test_coupling.py's: a fixed sphere in creeping flow (Re = 0.02) with the exact
Stokes solution on every boundary face, so the reference is 6πμaU with no wall correction.
"""
import csv
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from test_coupling import simulation, stokes_run  # noqa: E402  (the validation cases, not copies)
from pmpm.reference import square_duct_wall_factor, terminal_velocity  # noqa: E402

KNOBS = [  # forcing, cells per diameter, rule, forcing passes, diffusion number ν dt/h²
    ("penalty", 4, "nodes", 3, 0.1), ("penalty", 8, "nodes", 3, 0.1), ("penalty", 16, "nodes", 3, 0.1),
    ("penalty", 4, "subcell", 3, 0.1), ("penalty", 8, "subcell", 3, 0.1), ("penalty", 16, "subcell", 3, 0.1),
    ("penalty", 8, "subcell", 1, 0.1), ("penalty", 8, "subcell", 3, 0.025), ("penalty", 8, "subcell", 3, 0.4),
    ("penalty", 4, "subcell", 3, 0.025), ("penalty", 4, "subcell", 3, 0.4),
    ("patch", 8, "nodes", 3, 0.1), ("patch", 8, "subcell", 3, 0.1), ("patch", 8, "subcell", 1, 0.1),
    ("patch", 8, "subcell", 3, 0.025), ("patch", 8, "subcell", 3, 0.4), ("patch", 8, "subcell", 6, 0.4),
]


def main():
    if "--settling" in sys.argv:
        return settling()
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for forcing, cpd, rule, passes, diffusion in KNOBS:
        folder = Path(tempfile.mkdtemp())
        start = time.perf_counter()
        # the same simulated time at every step size: 40 steps at ν dt/h² = 0.1
        ratio = stokes_run(MPI.COMM_SELF, folder, cpd, rule, steps=int(round(4 / diffusion)),
                           diffusion_number=diffusion, forcing_passes=passes, forcing=forcing)
        seconds = time.perf_counter() - start
        rows.append(dict(forcing=forcing, cells_per_diameter=cpd, volume_fraction=rule, forcing_passes=passes,
                         diffusion_number=diffusion, drag_error=ratio[2] - 1, wall_seconds=seconds))
        print(f"{forcing:8s} {cpd:3d} cells/d  {rule:8s} passes {passes}  ν dt/h² {diffusion:5.3f}:  "
              f"drag error {100 * (ratio[2] - 1):+6.2f} %   {seconds:6.1f} s", flush=True)
    with open(out / "accuracy.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    for forcing, rule, marker in (("penalty", "nodes", "o"), ("penalty", "subcell", "s"),
                                  ("patch", "nodes", "^"), ("patch", "subcell", "v")):
        pick = [r for r in rows if (r["forcing"], r["volume_fraction"]) == (forcing, rule)]
        ax.scatter([r["wall_seconds"] for r in pick], [abs(r["drag_error"]) * 100 for r in pick], marker=marker,
                   label=f"{forcing}, {rule}")
        for r in pick:
            ax.annotate(f'{r["cells_per_diameter"]}/d, {r["forcing_passes"]}p, {r["diffusion_number"]}',
                        (r["wall_seconds"], abs(r["drag_error"]) * 100), fontsize=6)
    ax.set_xscale("log"); ax.set_yscale("log")
    ax.set_xlabel("wall time to t = 4 h²/ν (s)"); ax.set_ylabel("|drag error| (%)")
    ax.set_title("Stokes drag: error against cost"); ax.legend()
    fig.tight_layout(); fig.savefig(out / "accuracy.png", dpi=120)
    print(f"wrote {out / 'accuracy.csv'} and {out / 'accuracy.png'}")
    settling()


SETTLING = [  # viscosity (Re ≈ 8 or ≈ 1), cells per diameter, box width in diameters, forcing passes, ν dt/h²
    (0.1, 4, 6, 3, 0.1), (0.1, 4, 9, 3, 0.1), (0.1, 4, 12, 3, 0.1), (0.1, 6, 6, 3, 0.1), (0.1, 8, 6, 3, 0.1),
    (0.1, 4, 6, 6, 0.05),
    (0.4, 4, 6, 3, 0.1), (0.4, 4, 6, 3, 0.05), (0.4, 4, 6, 3, 0.025), (0.4, 4, 6, 6, 0.05), (0.4, 4, 6, 10, 0.025),
]


def settling(d=0.008, rho_p=1500.0, rho_f=1000.0):
    """A sphere (ρp/ρf = 1.5) settling from rest in a closed box of liquid, 2 widths tall, released
    1.7 widths up: the speed reached (0.6 s at Re ≈ 8, 0.2 s at Re ≈ 1: terminal, many diameters
    above the floor) against Schiller–Naumann (unbounded), over box width, resolution, forcing
    passes and time step. Writes bench/results/settling.csv."""
    rows = []
    for mu, cpd, widths, passes, diffusion in SETTLING:
        unbounded = terminal_velocity(rho_p, rho_f, mu, d)
        h = d / cpd
        n = int(round(widths * d / h))
        dt = diffusion * h * h * rho_f / mu
        width = n * h
        start = time.perf_counter()
        sim = simulation(MPI.COMM_SELF, Path(tempfile.mkdtemp()), L=width, H=2 * width, n=n, m=2 * n, mu=mu,
                         rho_f=rho_f, rho_p=rho_p, radius=d / 2, rule="subcell", gravity="[0.0, 0.0, -9.81]",
                         dt=dt, passes=passes, position=f"[{width / 2 + 0.1 * h}, {width / 2 - 0.2 * h}, {1.7 * width}]")
        for _ in range(int(round((0.6 if mu < 0.2 else 0.2) / dt))):
            sim.advance(dt)
        speed = -sim.particles.v[0, 2]
        walled = terminal_velocity(rho_p, rho_f, mu, d, wall_factor=square_duct_wall_factor(d / width))
        rows.append(dict(reynolds=round(rho_f * unbounded * d / mu, 2), cells_per_diameter=cpd, box_diameters=widths,
                         forcing_passes=passes, diffusion_number=diffusion, speed=speed,
                         speed_over_schiller_naumann=speed / unbounded,
                         speed_over_walled_reference=speed / walled, wall_seconds=time.perf_counter() - start))
        print(f"settling Re {rows[-1]['reynolds']:4.1f}, {cpd} cells/d, box {widths:2d} d, {passes:2d} passes, "
              f"ν dt/h² {diffusion:5.3f}: {speed:.4f} m/s = {speed / unbounded:.3f} × Schiller–Naumann unbounded "
              f"({unbounded:.4f}), {speed / walled:.3f} × that with the creeping square-duct wall factor "
              f"({walled:.4f}); {rows[-1]['wall_seconds']:.0f} s", flush=True)
    with open(ROOT / "bench" / "results" / "settling.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main()
