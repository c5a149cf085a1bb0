"""Where explicit particle–fluid coupling goes unstable, and whether the implicit update holds.

    .venv/bin/python bench/stability.py          # about 15 minutes on one core
    .venv/bin/python bench/stability.py --quick  # the default scheme at the light end, 2 minutes

A sphere (d = 8 mm) released at rest in a closed box of liquid (4 diameters wide, 8 tall) under
gravity, over density ratio ρp/ρf (1000 … 0.3), cells per diameter (2 … 16), time step (as the
diffusion number ν dt/h²), forcing and particle update (``[coupling] forcing, update``), 30 steps
each. A run is

* ``rings``  — the run stopped with exit-3 advice (the explicit update's ringing detector);
* ``blows``  — the particle velocity stopped being finite, or exceeded 10 × the Stokes speed;
* ``rings*`` — it finished, but its velocity increment changed sign more than 8 times;
* ``ok``     — a smooth start: what the physics gives.

Prints the table (docs/coupling.md has the measured one) and writes bench/results/stability.csv
(stability_quick.csv with --quick).
"""
import csv
import sys
import tempfile
from pathlib import Path

import numpy as np
from mpi4py import MPI

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from test_coupling import simulation  # noqa: E402  (the validation cases' case builder)
from pmpm.errors import NumericalError  # noqa: E402

RATIOS = (1000.0, 2.0, 1.2, 0.8, 0.6, 0.5, 0.4, 0.3)
RESOLUTIONS = (2, 4, 8, 16)
DIFFUSION = (0.1, 0.4)
SCHEMES = (("patch", "explicit"), ("penalty", "explicit"), ("penalty", "implicit"))  # [coupling] forcing, update
if "--quick" in sys.argv:   # the default scheme only, 2–8 cells per diameter, the light end
    SCHEMES, RESOLUTIONS, RATIOS = (("penalty", "implicit"),), (2, 4, 8), (1.2, 0.8, 0.5, 0.3, 0.1)


def run(ratio, cpd, diffusion, forcing, update, d=0.008, mu=0.5, rho_f=1000.0, steps=30):
    h = d / cpd
    n = int(round(4 * d / h)) if cpd < 16 else int(round(3 * d / h))
    dt = diffusion * h * h * rho_f / mu
    sim = simulation(MPI.COMM_SELF, Path(tempfile.mkdtemp()), L=n * h, H=2 * n * h, n=n, m=2 * n, mu=mu,
                     rho_f=rho_f, rho_p=ratio * rho_f, radius=d / 2, rule="subcell", update=update, forcing=forcing,
                     gravity="[0.0, 0.0, -9.81]", dt=dt, position=f"[{n * h / 2 + 0.1 * h}, {n * h / 2}, {n * h}]")
    stokes = abs(ratio - 1) * rho_f * 9.81 * d * d / (18 * mu)
    speeds = []
    try:
        for _ in range(steps):
            sim.advance(dt)
            if len(sim.particles) == 0:
                break                      # a heavy particle fell out of the box: no instability on the way
            speed = sim.particles.v[0, 2]
            if not np.isfinite(speed) or abs(speed) > 10 * stokes + 1e-12:
                return "blows"
            speeds.append(speed)
    except NumericalError:
        return "rings"
    flips = int(np.sum(np.diff(np.sign(np.diff(speeds))) != 0))
    return "rings*" if flips > 8 else "ok"


def main():
    rows = []
    for forcing, update in SCHEMES:
        for diffusion in DIFFUSION:
            for cpd in RESOLUTIONS:
                for ratio in RATIOS:
                    if cpd == 16 and ratio not in (1000.0, 0.6, 0.5, 0.4):
                        continue   # the 16-cells-per-diameter runs are slow: the threshold region only
                    outcome = run(ratio, cpd, diffusion, forcing, update)
                    rows.append(dict(forcing=forcing, update=update, diffusion_number=diffusion,
                                     cells_per_diameter=cpd, density_ratio=ratio, outcome=outcome))
                    print(f"{forcing:8s} {update:8s} ν dt/h² {diffusion:4.2f}  {cpd:2d} cells/d  ρp/ρf {ratio:7.1f}: "
                          f"{outcome}", flush=True)
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    with open(out / ("stability_quick.csv" if "--quick" in sys.argv else "stability.csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print("\n| forcing | update | ν dt/h² | cells per diameter | " + " | ".join(f"{r:g}" for r in RATIOS) + " |")
    print("|---|---|---|---|" + "---|" * len(RATIOS))
    for forcing, update in SCHEMES:
        for diffusion in DIFFUSION:
            for cpd in RESOLUTIONS:
                found = {r["density_ratio"]: r["outcome"] for r in rows
                         if (r["forcing"], r["update"], r["diffusion_number"], r["cells_per_diameter"])
                         == (forcing, update, diffusion, cpd)}
                print(f"| {forcing} | {update} | {diffusion:g} | {cpd} | "
                      + " | ".join(found.get(r, "") for r in RATIOS) + " |")


if __name__ == "__main__":
    main()
