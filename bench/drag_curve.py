"""The drag of a fixed sphere against the standard drag curve (Schiller–Naumann to Re 800,
Clift–Grace–Weber beyond) over Re 0.1–1000 at 3, 4, 6 and 8 cells per diameter, with the velocity
left inside the sphere and the wall time of each run. Writes bench/results/drag_curve.csv and
drag_curve.png and prints the table.

    OMP_NUM_THREADS=1 .venv/bin/python bench/drag_curve.py             # ≈ 1.5 h on one core
    .venv/bin/python bench/drag_curve.py --cells 3,4 --reynolds 1,100  # a subset
    .venv/bin/python bench/drag_curve.py --box-check                   # + the box's effect (4 cells/d)
    .venv/bin/python bench/drag_curve.py --reynolds 100 --keep bench/results/drag_curve.csv   # redo some
    mpirun -n 2 .venv/bin/python bench/drag_curve.py --cells 8         # any run on several ranks
    .venv/bin/python bench/drag_curve.py --correction di_felice --output bench/results/drag_curve_di_felice
                                                                       # with the drag correction

The case is tests/test_coupling.py's ``stream_run``: a sphere held off the lattice in a box 8
diameters wide, 4 upstream and 6 downstream of it, Oseen's flow (with the standard curve's drag) on
the inlet and the sides, an outlet downstream; sub-cell volume fractions, the default penalty
forcing, linear-upwind convection; dt the smaller of CFL 0.5 (0.25 from Re 300: explicit convection
at cell Reynolds numbers ≫ 1) and ν dt/h² = 0.4; the drag averaged over the last quarter of 8 d/U
(24 d/U from Re 100; 2 d²/ν at low Re, where the flow is steady within a viscous time). ``--box-check`` repeats the 4
cells-per-diameter runs in a box 12 d wide, 6 up- and 9 downstream, and prints the ratio.
``--correction`` switches on the drag correction for under-resolved particles; the table then also
gives the error against the correlation's own drag of a lone sphere (ε = 1).
"""
import argparse
import csv
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from test_coupling import stream_run  # noqa: E402  (the validation case, not a copy)
from pmpm.errors import NumericalError  # noqa: E402
from pmpm.coupling.correction import CORRELATIONS  # noqa: E402
from pmpm.reference import standard_drag_coefficient  # noqa: E402

REYNOLDS = (0.1, 1.0, 10.0, 30.0, 100.0, 300.0, 1000.0)
CELLS = (3, 4, 6, 8)
BOX, BIG_BOX = (8.0, 4.0, 6.0), (12.0, 6.0, 9.0)
DIAMETER, SPEED, DENSITY = 0.02, 0.1, 1000.0


def run(comm, reynolds, cells, box, forcing, correction="off"):
    folder = Path(comm.bcast(tempfile.mkdtemp() if comm.rank == 0 else None))
    viscosity = DENSITY * SPEED * DIAMETER / reynolds
    start = time.perf_counter()
    # from Re 100 the wake takes long to settle (4 cells/d, Re 300: −6 % from 8 to 24 d/U) and from
    # Re 300 it is unsteady: average over the last 6 d/U of 24
    result = stream_run(comm, folder, SPEED, cells, DENSITY, viscosity, diameter=DIAMETER, box=box,
                        cfl=0.25 if reynolds >= 300 else 0.5, flow_times=24.0 if reynolds >= 100 else 8.0,
                        forcing=forcing, correction=correction)
    return result, time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", default=",".join(map(str, CELLS)), help="cells per diameter, comma-separated")
    parser.add_argument("--reynolds", default=",".join(map(str, REYNOLDS)), help="Reynolds numbers, comma-separated")
    parser.add_argument("--box-check", action="store_true", help="also the 4 cells/d runs in a 1.5× larger box")
    parser.add_argument("--forcing", default="penalty", choices=("penalty", "patch"))
    parser.add_argument("--correction", default="off", choices=("off", *CORRELATIONS))
    parser.add_argument("--output", default=str(ROOT / "bench" / "results" / "drag_curve"),
                        help="CSV and PNG path without suffix")
    parser.add_argument("--keep", default=None,
                        help="an earlier CSV whose runs (Re, cells/d) not repeated here join the table")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    cells = [int(c) for c in args.cells.split(",")]
    numbers = [float(r) for r in args.reynolds.split(",")]
    rows = []
    for cpd in cells:
        for reynolds in numbers:
            try:
                result, seconds = run(comm, reynolds, cpd, BOX, args.forcing, args.correction)
            except NumericalError as failure:     # the explicit convection at high cell Re: say so, go on
                if comm.rank == 0:
                    print(f"Re {reynolds:7.1f}, {cpd} cells/d: failed: {failure}", flush=True)
                rows.append(dict(reynolds=reynolds, cells_per_diameter=cpd, forcing=args.forcing, error=np.nan,
                                 note=str(failure)[:120]))
                continue
            standard = float(standard_drag_coefficient(reynolds))
            row = dict(reynolds=reynolds, cells_per_diameter=cpd, forcing=args.forcing, correction=args.correction,
                       drag_coefficient=round(result["drag_coefficient"], 5), standard=round(standard, 5),
                       error=round(result["drag_coefficient"] / standard - 1, 4),
                       inside=round(result["inside"], 5), centre_inside=round(result["centre_inside"], 4),
                       diffusion_number=round(result["diffusion_number"], 4), steps=result["steps"],
                       ranks=comm.size, wall_seconds=round(seconds, 1))
            if args.correction != "off":   # the correlation's lone sphere: C_D = 24 F/Re
                alone = 24.0 * float(CORRELATIONS[args.correction](0.0, reynolds)) / reynolds
                row["correlation_error"] = round(result["drag_coefficient"] / alone - 1, 4)
            if args.box_check and cpd == 4:
                big, _ = run(comm, reynolds, cpd, BIG_BOX, args.forcing, args.correction)
                row["larger_box_ratio"] = round(big["drag_coefficient"] / result["drag_coefficient"], 4)
            rows.append(row)
            if comm.rank == 0:
                extra = f", 1.5× box: ×{row['larger_box_ratio']:.3f}" if "larger_box_ratio" in row else ""
                if "correlation_error" in row:
                    extra += f", against {args.correction} alone {100 * row['correlation_error']:+6.1f} %"
                print(f"Re {reynolds:7.1f}, {cpd} cells/d: C_D {row['drag_coefficient']:9.4f}, standard {standard:9.4f}, "
                      f"error {100 * row['error']:+6.1f} %; inside ≤ {100 * row['inside']:.2f} % of U, centres inside "
                      f"{100 * row['centre_inside']:.1f} %{extra}; {row['steps']} steps, {seconds:.1f} s on "
                      f"{comm.size} rank(s)", flush=True)
    if comm.rank:
        return
    if args.keep:
        done = {(r["reynolds"], r["cells_per_diameter"]) for r in rows}
        with open(args.keep) as f:
            kept = [{k: v for k, v in r.items() if v != ""} for r in csv.DictReader(f)]
        for r in kept:
            for key in ("reynolds", "drag_coefficient", "standard", "error", "inside", "centre_inside",
                        "diffusion_number", "wall_seconds", "larger_box_ratio", "correlation_error"):
                if key in r:
                    r[key] = float(r[key])
            r["cells_per_diameter"] = int(r["cells_per_diameter"])
        rows += [r for r in kept if (r["reynolds"], r["cells_per_diameter"]) not in done]
        rows.sort(key=lambda r: (r["cells_per_diameter"], r["reynolds"]))
        cells = sorted({r["cells_per_diameter"] for r in rows})
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    fields = list(dict.fromkeys(k for row in rows for k in row))
    with open(out.with_suffix(".csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    curve = np.logspace(-1, 3, 200)
    left.plot(curve, standard_drag_coefficient(curve), "k-", linewidth=1, label="standard curve")
    for k, cpd in enumerate(cells):
        pick = [r for r in rows if r["cells_per_diameter"] == cpd and "drag_coefficient" in r]
        x = [r["reynolds"] for r in pick]
        left.plot(x, [r["drag_coefficient"] for r in pick], "o", color=f"C{k}", label=f"{cpd} cells/d")
        right.plot(x, [100 * r["error"] for r in pick], "o-", color=f"C{k}", label=f"{cpd} cells/d")
    left.set_xscale("log"); left.set_yscale("log")
    left.set_xlabel("Re"); left.set_ylabel("$C_D$"); left.legend(fontsize=7)
    right.axhline(0, color="k", linewidth=0.8)
    right.set_xscale("log"); right.set_xlabel("Re"); right.set_ylabel("drag / standard − 1 (%)")
    right.legend(fontsize=7)
    corrected = "" if args.correction == "off" else f", drag correction {args.correction}"
    fig.suptitle(f"fixed sphere, {args.forcing} forcing, sub-cell volume fractions{corrected}", fontsize=9)
    fig.tight_layout(); fig.savefig(out.with_suffix(".png"), dpi=120)
    print(f"wrote {out.with_suffix('.csv')} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
