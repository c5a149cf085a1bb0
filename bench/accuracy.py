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
from pmpm.reference import di_felice_wall_factor, terminal_velocity  # noqa: E402

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


SETTLING = [  # viscosity (Re ≈ 0.8, 8.5, 24), cells per diameter, box width and height in diameters, CFL, time
    (0.4, 4, 6, 24, 0.1, 0.5), (0.1, 4, 6, 24, 0.3, 0.6), (0.1, 6, 6, 24, 0.3, 0.6), (0.1, 4, 12, 24, 0.3, 0.6),
    (0.05, 4, 8, 32, 0.3, 0.8),
]


def settling(d=0.008, rho_p=1500.0, rho_f=1000.0):
    """A sphere (ρp/ρf = 1.5) settling from rest in a tall closed box of liquid, released 6 d below
    the lid: its speed at the end (terminal: it changes by < 0.5 % over the last fifth) against
    Schiller–Naumann × the Di Felice (1996) wall factor for a tube of equal area. The time step
    follows the CFL number at the reference speed. Writes bench/results/settling.csv."""
    rows = []
    for mu, cpd, widths, heights, cfl, end_time in SETTLING:
        unbounded = terminal_velocity(rho_p, rho_f, mu, d)
        reynolds = rho_f * unbounded * d / mu
        h = d / cpd
        n, m = int(round(widths * cpd)), int(round(heights * cpd))
        dt = cfl * h / unbounded
        width, height = n * h, m * h
        start = time.perf_counter()
        sim = simulation(MPI.COMM_SELF, Path(tempfile.mkdtemp()), L=width, H=height, n=n, m=m, mu=mu,
                         rho_f=rho_f, rho_p=rho_p, radius=d / 2, rule="subcell", gravity="[0.0, 0.0, -9.81]",
                         dt=dt, position=f"[{width / 2 + 0.1 * h}, {width / 2 - 0.2 * h}, {height - 6 * d}]")
        steps = int(round(end_time / dt))
        speeds = []
        for _ in range(steps):
            sim.advance(dt)
            speeds.append(-sim.particles.v[0, 2])
        speed, earlier = speeds[-1], speeds[-max(1, steps // 5)]
        walled = unbounded * di_felice_wall_factor(d / (width * 2 / np.sqrt(np.pi)), reynolds)
        rows.append(dict(reynolds=round(reynolds, 2), cells_per_diameter=cpd, box_diameters=widths,
                         diffusion_number=round(mu / rho_f * dt / h ** 2, 3), speed=speed,
                         last_fifth_change=speed / earlier - 1, speed_over_schiller_naumann=speed / unbounded,
                         speed_over_walled_reference=speed / walled, wall_seconds=time.perf_counter() - start))
        print(f"settling Re {reynolds:4.1f}, {cpd} cells/d, box {widths:2d} d × {heights} d, ν dt/h² "
              f"{rows[-1]['diffusion_number']:.3f}: {speed:.4f} m/s (last fifth {100 * (speed / earlier - 1):+.2f} %) = "
              f"{speed / unbounded:.3f} × Schiller–Naumann unbounded ({unbounded:.4f}), {speed / walled:.3f} × "
              f"that with the Di Felice wall factor ({walled:.4f}); {rows[-1]['wall_seconds']:.0f} s", flush=True)
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "settling.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main()
