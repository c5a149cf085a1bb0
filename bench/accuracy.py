"""Speed against accuracy of the particle coupling: Stokes drag error against wall time over the
knobs (forcing, cells per diameter, volume-fraction rule, forcing passes, time step as the
diffusion number ν dt/h²). Writes bench/results/accuracy.csv and accuracy.png and prints the table.

    .venv/bin/python bench/accuracy.py            # about 20 minutes on one core (--settling: that part only)
    mpirun -n 2 .venv/bin/python bench/accuracy.py --settling --fine     # adds 8 cells per diameter
    .venv/bin/python bench/accuracy.py --body-fitted   # the OpenFOAM reference for settling (≈ 3 min)
    .venv/bin/python bench/accuracy.py --suspensions   # the packed bed against Ergun (≈ 15 min)

The case is tests/test_coupling.py's: a fixed sphere in creeping flow (Re = 0.02) with the exact
Stokes solution on every boundary face, so the reference is 6πμaU with no wall correction. Then
settling (``settling``) in ten Cate et al.'s (2002) box, against a body-fitted OpenFOAM solution
(``body_fitted``) and their measured terminal speeds. ``--suspensions``: a dense case, the
pressure drop through a fixed random packed bed against Ergun's (bench/suspensions.py's case) at
Re 10 and 100, one knob changed at a time from 3 cells per diameter, penalty, sub-cell fractions,
one pass, no correction (``suspensions``; suspensions_accuracy.csv and .png).
"""
import csv
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results"
sys.path.insert(0, str(ROOT / "tests"))
from test_coupling import stokes_run, ten_cate_run  # noqa: E402  (the validation cases, not copies)
from suspension_cases import packed_bed  # noqa: E402
from pmpm.reference import di_felice_wall_factor, ergun_pressure_drop, terminal_velocity  # noqa: E402

KNOBS = [  # forcing, cells per diameter, rule, forcing passes, diffusion number ν dt/h²
    ("penalty", 4, "nodes", 3, 0.1), ("penalty", 8, "nodes", 3, 0.1), ("penalty", 16, "nodes", 3, 0.1),
    ("penalty", 4, "subcell", 3, 0.1), ("penalty", 8, "subcell", 3, 0.1), ("penalty", 16, "subcell", 3, 0.1),
    ("penalty", 8, "subcell", 1, 0.1), ("penalty", 8, "subcell", 3, 0.025), ("penalty", 8, "subcell", 3, 0.4),
    ("penalty", 4, "subcell", 3, 0.025), ("penalty", 4, "subcell", 3, 0.4),
    ("patch", 8, "nodes", 3, 0.1), ("patch", 8, "subcell", 3, 0.1), ("patch", 8, "subcell", 1, 0.1),
    ("patch", 8, "subcell", 3, 0.025), ("patch", 8, "subcell", 3, 0.4), ("patch", 8, "subcell", 6, 0.4),
]


def write_csv(name: str, rows: list[dict]):
    """Write ``rows`` (dicts with the same keys) as CSV to bench/results/``name``; return
    matplotlib.pyplot (Agg) for the figure that goes with them."""
    OUT.mkdir(parents=True, exist_ok=True)
    with open(OUT / name, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def main():
    if "--settling" in sys.argv:
        return settling()
    if "--body-fitted" in sys.argv:
        return body_fitted()
    if "--suspensions" in sys.argv:
        return suspensions()
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
    plt = write_csv("accuracy.csv", rows)
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
    fig.tight_layout(); fig.savefig(OUT / "accuracy.png", dpi=120)
    print(f"wrote {OUT / 'accuracy.csv'} and {OUT / 'accuracy.png'}")
    settling()


SUSPENSION_KNOBS = [  # cells per diameter, forcing, forcing passes, volume-fraction rule, drag correction
    (3, "penalty", 1, "subcell", "off"), (4, "penalty", 1, "subcell", "off"), (6, "penalty", 1, "subcell", "off"),
    (3, "patch", 1, "subcell", "off"), (3, "patch", 3, "subcell", "off"), (3, "penalty", 3, "subcell", "off"),
    (3, "penalty", 1, "nodes", "off"), (3, "penalty", 1, "subcell", "di_felice"),
    (3, "penalty", 1, "subcell", "beetstra"), (4, "penalty", 1, "subcell", "di_felice"),
    (3, "penalty", 1, "nodes", "di_felice"),
]


def suspensions(comm=MPI.COMM_WORLD):
    """The packed bed's pressure drop against Ergun's, one knob at a time (``SUSPENSION_KNOBS``), at
    particle Reynolds numbers 10 and 100: error against wall time. Writes
    bench/results/suspensions_accuracy.csv and suspensions_accuracy.png and prints the table."""
    rows = []
    for cpd, forcing, passes, rule, correction in SUSPENSION_KNOBS:
        for reynolds in (10.0, 100.0):
            folder = Path(comm.bcast(tempfile.mkdtemp() if comm.rank == 0 else None))
            coupling = {} if correction == "off" else {"drag_correction": correction}
            start = time.perf_counter()
            result = packed_bed(comm, folder, cpd, reynolds, rule=rule, forcing=forcing, passes=passes,
                                coupling=coupling, flow_times=1.0, min_steps=150, max_steps=300)
            seconds = time.perf_counter() - start
            ergun = float(ergun_pressure_drop(result["speed"], result["porosity"], result["diameter"],
                                              result["density"], result["viscosity"]))
            rows.append(dict(reynolds=reynolds, cells_per_diameter=cpd, forcing=forcing, forcing_passes=passes,
                             volume_fraction=rule, drag_correction=correction, error=result["gradient"] / ergun - 1,
                             steps=result["steps"], wall_seconds=seconds, seconds_per_step=result["seconds"] / result["steps"],
                             ranks=comm.size))
            if comm.rank == 0:
                print(f"Re {reynolds:5.0f}  {cpd} cells/d  {forcing:8s} passes {passes}  {rule:8s} correction "
                      f"{correction:10s}: −dp/dz error against Ergun {100 * rows[-1]['error']:+6.1f} %  "
                      f"{seconds:6.1f} s ({rows[-1]['seconds_per_step']:.3f} s/step)", flush=True)
    if comm.rank:
        return
    plt = write_csv("suspensions_accuracy.csv", rows)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, reynolds in zip(axes, (10.0, 100.0)):
        pick = [r for r in rows if r["reynolds"] == reynolds]
        for r in pick:
            marker = "s" if r["drag_correction"] != "off" else ("^" if r["forcing"] == "patch" else "o")
            ax.scatter(r["wall_seconds"], abs(r["error"]) * 100, marker=marker, color="C1" if marker == "s" else "C0")
            ax.annotate(f'{r["cells_per_diameter"]}/d {r["forcing"]} {r["forcing_passes"]}p {r["volume_fraction"]} '
                        f'{r["drag_correction"]}', (r["wall_seconds"], abs(r["error"]) * 100), fontsize=5)
        ax.set_xscale("log"); ax.set_yscale("log")
        ax.set_xlabel("wall time of the run (s, 1 rank)"); ax.set_title(f"packed bed against Ergun, Re {reynolds:.0f}")
    axes[0].set_ylabel("|−dp/dz error| (%)")
    fig.tight_layout(); fig.savefig(OUT / "suspensions_accuracy.png", dpi=120)
    print(f"wrote {OUT / 'suspensions_accuracy.csv'} and {OUT / 'suspensions_accuracy.png'}")


SETTLING_CELLS_ACROSS = (27, 41)        # 4 and 6 cells per diameter in ten Cate's box; --fine adds 53 (8)


def settling(comm=MPI.COMM_WORLD):
    """ten Cate et al.'s (2002) four settling experiments (Re 1.5–32) in their box, at 4 and 6
    cells per diameter (with --fine also 8; run that under mpirun), against the body-fitted
    Navier–Stokes terminal speeds (``body_fitted``) and the measured ones; Schiller–Naumann
    unbounded and × the Di Felice (1996) tube factor (equal area) for comparison. Writes
    bench/results/settling.csv and settling.png (speed against time)."""
    from pmpm.reference import TEN_CATE_2002, TEN_CATE_BODY_FITTED, TEN_CATE_BOX, TEN_CATE_SPHERE

    d, rho_p, _ = TEN_CATE_SPHERE
    cells = SETTLING_CELLS_ACROSS + ((53,) if "--fine" in sys.argv else ())
    rows, curves = [], {}
    for n in cells:
        for experiment, (rho_f, mu, measured) in TEN_CATE_2002.items():
            folder = Path(comm.bcast(tempfile.mkdtemp() if comm.rank == 0 else None))
            start = time.perf_counter()
            times, speeds, _ = ten_cate_run(comm, folder, experiment, n)
            seconds = time.perf_counter() - start
            top = speeds.max()
            unbounded = terminal_velocity(rho_p, rho_f, mu, d)
            reynolds = rho_f * measured * d / mu
            walled = unbounded * di_felice_wall_factor(d / (TEN_CATE_BOX[0] * 2 / np.sqrt(np.pi)), reynolds)
            h = TEN_CATE_BOX[0] / n
            rows.append(dict(experiment=experiment, reynolds=round(reynolds, 1), cells_per_diameter=round(d / h, 2),
                             diffusion_number=round(mu / rho_f * (times[1] - times[0]) / h ** 2, 3),
                             largest_speed=top, body_fitted=TEN_CATE_BODY_FITTED[experiment],
                             error=top / TEN_CATE_BODY_FITTED[experiment] - 1,
                             measured=measured, error_to_measured=top / measured - 1,
                             schiller_naumann_unbounded=unbounded, with_di_felice=walled,
                             ranks=comm.size, wall_seconds=seconds))
            curves[experiment, n] = (times, speeds)
            if comm.rank == 0:
                print(f"ten Cate {experiment} (Re {reynolds:4.1f}), {d / h:.2f} cells/d, ν dt/h² "
                      f"{rows[-1]['diffusion_number']:.3f}: largest speed {top:.4f} m/s, body-fitted "
                      f"{TEN_CATE_BODY_FITTED[experiment]} ({100 * rows[-1]['error']:+.1f} %), measured {measured} "
                      f"({100 * (top / measured - 1):+.1f} %); Schiller–Naumann {unbounded:.4f}, × Di Felice "
                      f"{walled:.4f}; {seconds:.0f} s on {comm.size} rank(s)", flush=True)
    if comm.rank:
        return
    plt = write_csv("settling.csv", rows)
    fig, ax = plt.subplots(figsize=(6, 4))
    for k, (experiment, (_, _, measured)) in enumerate(TEN_CATE_2002.items()):
        colour = f"C{k}"
        ax.axhline(measured, color=colour, linestyle=":", linewidth=1)
        ax.axhline(TEN_CATE_BODY_FITTED[experiment], color="0.5", linestyle="--", linewidth=0.8)
        for n, style in zip(cells, ("--", "-", "-.")):
            times, speeds = curves[experiment, n]
            ax.plot(times, speeds, style, color=colour, linewidth=1,
                    label=f"{experiment}, {TEN_CATE_SPHERE[0] * n / TEN_CATE_BOX[0]:.0f} cells/d")
    ax.set_xlabel("t (s)"); ax.set_ylabel("settling speed (m/s)")
    ax.set_title("ten Cate et al. 2002 (dotted: measured, dashed grey: body-fitted terminal speed)", fontsize=8)
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout(); fig.savefig(OUT / "settling.png", dpi=120)
    print(f"wrote {OUT / 'settling.csv'} and {OUT / 'settling.png'}")


def body_fitted(slower=0.92):
    """The body-fitted reference of ``pmpm.reference.TEN_CATE_BODY_FITTED``, recomputed with OpenFOAM
    (bench/openfoam_sphere_duct.sh, spawns mpirun itself: run this serially, ≈ 3 minutes): for each
    experiment the drag on the held sphere at the measured speed and at ``slower`` × it, and the
    speed where the power law through them meets the weight less buoyancy."""
    import os
    import subprocess
    from pmpm.reference import TEN_CATE_2002, TEN_CATE_BODY_FITTED, TEN_CATE_SPHERE

    d, rho_p, _ = TEN_CATE_SPHERE
    # this process has initialised MPI (mpi4py); the script's own mpirun must not see its variables
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_", "PMI_"))}
    for experiment, (rho_f, mu, measured) in TEN_CATE_2002.items():
        speeds = np.array([measured, slower * measured])
        drags = []
        for speed in speeds:
            line = subprocess.run([str(ROOT / "bench" / "openfoam_sphere_duct.sh"), str(rho_f), str(mu), f"{speed:.6g}"],
                                  check=True, capture_output=True, text=True, env=env).stdout.split()
            drags.append(float(dict(item.split("=") for item in line[1:])["drag"]))
        weight = (rho_p - rho_f) * np.pi * d ** 3 / 6 * 9.81
        exponent = np.log(drags[0] / drags[1]) / np.log(speeds[0] / speeds[1])
        terminal = speeds[1] * (weight / drags[1]) ** (1 / exponent)
        print(f"ten Cate {experiment}: body-fitted drag {drags[0]:.4e} N at {speeds[0]:.4g} m/s, {drags[1]:.4e} N at "
              f"{speeds[1]:.4g} m/s; weight less buoyancy {weight:.4e} N → terminal speed {terminal:.4f} m/s "
              f"(stored {TEN_CATE_BODY_FITTED[experiment]}, measured {measured})", flush=True)


if __name__ == "__main__":
    main()
