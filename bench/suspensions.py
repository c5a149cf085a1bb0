"""Dense suspensions against the classical references (issue 12 part 2): the pressure drop through
a fixed random packed bed against Ergun's equation at particle Reynolds numbers 1–500 and 3, 4, 6
cells per diameter, with and without the drag correction; the minimum fluidization velocity of
that bed (glass beads, 3 mm, in water) against Wen & Yu; the expansion of the liquid-fluidized bed
against Richardson & Zaki at two inlet velocities. Writes bench/results/suspensions_ergun.csv,
suspensions_fluidized.csv and suspensions.png, and prints the tables.

    .venv/bin/python bench/suspensions.py              # everything: about 2 h on one core of the loaded machine
    .venv/bin/python bench/suspensions.py --ergun      # the packed bed only (--cells 3 --reynolds 1,10 --corrections off: those)
    .venv/bin/python bench/suspensions.py --fluidized  # the fluidized bed only (--speeds 0.1 --corrections off: that one)
    .venv/bin/python bench/suspensions.py --plot       # U_mf and the figure again from the CSVs

The cases are tests/suspension_cases.py's (the tests run short versions of the same): a column
4 diameters square with symmetry sides, d = 3 mm, water (ρ = 1000 kg/m³, μ = 1 mPa s), so the
particle Reynolds number ρ U d/μ = 100 is U = 33 mm/s, and Wen & Yu's onset for 2500 kg/m³ glass
(Re_mf = 98) lies in the sweep.
"""
import csv
import sys
import tempfile
from pathlib import Path

import numpy as np
from mpi4py import MPI

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from suspension_cases import fluidized_bed, packed_bed  # noqa: E402  (the validation cases, not copies)
from pmpm.reference import (ergun_minimum_fluidization, ergun_pressure_drop, richardson_zaki_exponent,  # noqa: E402
                            richardson_zaki_voidage, terminal_velocity, wen_yu_minimum_fluidization)

OUT = ROOT / "bench" / "results"
DIAMETER, RHO_F, MU, RHO_P, G = 0.003, 1000.0, 1e-3, 2500.0, 9.81
REYNOLDS = (1.0, 10.0, 100.0, 500.0)
CORRECTIONS = ("off", "di_felice")
FLUIDIZING = (0.06, 0.10)      # m/s: about 1.8 and 3 × Wen & Yu's U_mf


def print0(*args):
    if MPI.COMM_WORLD.rank == 0:
        print(*args, flush=True)


def write_csv(path: Path, rows: list[dict]) -> None:
    if MPI.COMM_WORLD.rank == 0 and rows:
        with open(path, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


def merge_csv(name: str, rows: list[dict], key) -> list[dict]:
    """Write ``rows`` into bench/results/``name``, keeping the rows already there whose ``key`` (a
    function of a row) none of ``rows`` has: parts of the sweep run apart (``--cells``,
    ``--reynolds``, ``--speeds``) fill one table. Returns the table."""
    mine = {key(r) for r in rows}
    table = sorted([r for r in read_csv(name) if key(r) not in mine] + rows, key=key)
    write_csv(OUT / name, table)
    return table


ERGUN_KEY = (lambda r: (float(r["cells_per_diameter"]), float(r["reynolds"]), r["correction"]))
FLUIDIZED_KEY = (lambda r: (float(r["speed"]), r["correction"], float(r["dt"])))


def ergun_row(cells_per_diameter: int, reynolds: float, correction: str, **options) -> dict:
    """One packed-bed run: the measured −dp/dz against Ergun's at the bed's own voidage."""
    coupling = {} if correction == "off" else {"drag_correction": correction}
    result = packed_bed(MPI.COMM_WORLD, Path(tempfile.mkdtemp()), cells_per_diameter, reynolds, coupling=coupling,
                        flow_times=1.0, min_steps=150, max_steps=300, **options)
    ergun = float(ergun_pressure_drop(result["speed"], result["porosity"], DIAMETER, RHO_F, MU))
    tail = result["history"][-max(1, result["steps"] // 5):]
    return dict(cells_per_diameter=cells_per_diameter, reynolds=reynolds, correction=correction,
                porosity=round(result["porosity"], 4), gradient=result["gradient"], ergun=ergun,
                ratio=result["gradient"] / ergun, drift=(tail[-1] - tail[0]) / ergun, steps=result["steps"],
                cells=result["cells"], particles=result["particles"], wall_seconds=result["seconds"],
                seconds_per_step=result["seconds"] / result["steps"])


def ergun(cells=(3, 4, 6), reynolds_numbers=REYNOLDS, corrections=CORRECTIONS) -> list[dict]:
    rows, table = [], []
    print0("cells/d  Re     correction  ε      −dp/dz / Ergun  drift   steps  cells   s/step  (1 rank)")
    for cpd in cells:
        for reynolds in reynolds_numbers:
            for correction in corrections:
                row = ergun_row(cpd, reynolds, correction)
                rows.append(row)
                if MPI.COMM_WORLD.rank == 0:     # as it goes: a long run keeps what it did
                    table = merge_csv("suspensions_ergun.csv", rows, ERGUN_KEY)
                print0(f"{cpd:5d} {reynolds:6.0f}   {correction:10s} {row['porosity']:.3f}   {row['ratio']:6.3f}"
                       f"         {row['drift']:+.3f}  {row['steps']:5d} {row['cells']:6d}  {row['seconds_per_step']:.3f}")
    return MPI.COMM_WORLD.bcast(table)


def minimum_fluidization(rows: list[dict]) -> list[dict]:
    """U_mf where each configuration's measured fixed-bed pressure drop (log-log between the swept
    Reynolds numbers) carries the bed's buoyant weight (1 − ε)(ρp − ρf) g: the balance that
    defines the onset and that Wen & Yu's correlation fits."""
    out = []
    wen_yu = float(wen_yu_minimum_fluidization(RHO_P, RHO_F, MU, DIAMETER, G))
    for cpd in sorted({r["cells_per_diameter"] for r in rows}):
        for correction in sorted({r["correction"] for r in rows}, key=lambda c: (c != "off", c)):
            sweep = sorted((r for r in rows if r["cells_per_diameter"] == cpd and r["correction"] == correction),
                           key=lambda r: r["reynolds"])
            if len(sweep) < 2:
                continue
            eps = float(np.mean([r["porosity"] for r in sweep]))
            weight = (1 - eps) * (RHO_P - RHO_F) * G
            speed = np.array([r["reynolds"] * MU / (RHO_F * DIAMETER) for r in sweep])
            gradient = np.array([r["gradient"] for r in sweep])
            # the onset: log(gradient) linear in log(U) between the two points that bracket the weight
            u_mf = float(np.exp(np.interp(np.log(weight), np.log(gradient), np.log(speed))))
            ergun_mf = float(ergun_minimum_fluidization(RHO_P, RHO_F, MU, DIAMETER, eps, G))
            out.append(dict(cells_per_diameter=cpd, correction=correction, porosity=round(eps, 4), u_mf=u_mf,
                            wen_yu=wen_yu, ratio_wen_yu=u_mf / wen_yu, ergun_at_porosity=ergun_mf,
                            ratio_ergun=u_mf / ergun_mf))
    print0("\ncells/d  correction  U_mf (m/s)  / Wen & Yu (%.4f)  / Ergun at the bed's ε" % wen_yu)
    for r in out:
        print0(f"{int(r['cells_per_diameter']):5d}   {r['correction']:10s}  {r['u_mf']:.4f}      {r['ratio_wen_yu']:.3f}"
               f"               {r['ratio_ergun']:.3f} (ε = {r['porosity']:.3f})")
    return out


def fluidized(speeds=FLUIDIZING, corrections=CORRECTIONS, dt: float = 1e-3) -> list[dict]:
    """The liquid-fluidized bed at two inlet velocities (``speeds``), with and without the
    correction."""
    u_t = float(terminal_velocity(RHO_P, RHO_F, MU, DIAMETER, G))
    n = float(richardson_zaki_exponent(RHO_F * u_t * DIAMETER / MU))
    rows, table = [], []
    print0(f"\nfluidized bed: U_t = {u_t:.4f} m/s (Schiller–Naumann), n = {n:.3f} (Garside & Al-Dibouni)")
    print0("U (m/s)  correction  ε measured  ε Richardson–Zaki  H/H_packed  lowest centre/r  s/step  (1 rank)")
    for speed in speeds:
        for correction in corrections:
            coupling = {} if correction == "off" else {"drag_correction": correction}
            try:
                r = fluidized_bed(MPI.COMM_WORLD, Path(tempfile.mkdtemp()), speed, dt=dt, duration=1.0, average=0.4,
                                  coupling=coupling)
            except ValueError as error:      # every particle gone: the run blew up
                print0(f"{speed:6.3f}   {correction:10s}  blew up (dt = {dt:g} s): {error}")
                continue
            reference = float(richardson_zaki_voidage(speed, u_t, n))
            rows.append(dict(speed=speed, correction=correction, dt=dt, voidage=r["voidage"], richardson_zaki=reference,
                             n=n, terminal_speed=u_t,
                             error=r["voidage"] - reference, expansion=r["height"] / r["packed_height"],
                             packed_voidage=r["packed_voidage"], lowest_over_radius=r["lowest"] / (DIAMETER / 2),
                             particles=r["particles"], remaining=r["remaining"], cells=r["cells"], steps=r["steps"],
                             wall_seconds=r["seconds"], seconds_per_step=r["seconds"] / r["steps"]))
            if MPI.COMM_WORLD.rank == 0:
                table = merge_csv("suspensions_fluidized.csv", rows, FLUIDIZED_KEY)
            print0(f"{speed:6.3f}   {correction:10s}  {r['voidage']:.3f}       {reference:.3f}             "
                   f"{r['height'] / r['packed_height']:.3f}       {r['lowest'] / (DIAMETER / 2):.3f}"
                   f"           {r['seconds'] / r['steps']:.3f}")
    return MPI.COMM_WORLD.bcast(table)


def plot(ergun_rows: list[dict], fluidized_rows: list[dict]) -> None:
    if MPI.COMM_WORLD.rank != 0:
        return
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    corrections = sorted({r["correction"] for r in ergun_rows + fluidized_rows}, key=lambda c: (c != "off", c))
    for cpd, colour in zip((3, 4, 6), ("C0", "C1", "C2")):
        for correction, style in zip(corrections, ("o-", "s--", "^:", "v-.")):
            rows = [r for r in ergun_rows if r["cells_per_diameter"] == cpd and r["correction"] == correction]
            if rows:
                left.plot([r["reynolds"] for r in rows], [r["ratio"] for r in rows], style, color=colour,
                          label=f"{cpd} cells/d, correction {correction}")
    left.axhline(1.0, color="k", lw=0.8)
    left.set(xscale="log", xlabel="particle Reynolds number ρUd/μ", ylabel="−dp/dz / Ergun",
             title="fixed packed bed")
    left.legend(fontsize=7)
    if fluidized_rows:
        u_t = float(terminal_velocity(RHO_P, RHO_F, MU, DIAMETER, G))
        n = float(richardson_zaki_exponent(RHO_F * u_t * DIAMETER / MU))
        speeds = np.linspace(0.03, 0.15, 50)
        right.plot(speeds, richardson_zaki_voidage(speeds, u_t, n), "k-", label="Richardson & Zaki")
        for correction, marker in zip(corrections, ("o", "s", "^", "v")):
            rows = [r for r in fluidized_rows if r["correction"] == correction]
            right.plot([r["speed"] for r in rows], [r["voidage"] for r in rows], marker,
                       label=f"pmpm, 3 cells/d, correction {correction}")
        right.axvline(float(wen_yu_minimum_fluidization(RHO_P, RHO_F, MU, DIAMETER, G)), color="grey", ls=":",
                      label="U_mf, Wen & Yu")
        right.set(xlabel="inlet (superficial) velocity U (m/s)", ylabel="bed voidage ε",
                  title="liquid-fluidized bed, glass 3 mm in water")
        right.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(OUT / "suspensions.png", dpi=120)


def read_csv(name: str) -> list[dict]:
    """The rows of bench/results/``name`` (numbers as floats), or none if it is not there."""
    path = OUT / name
    if not path.exists():
        return []
    with open(path) as f:
        return [{k: (v if k == "correction" else float(v or "nan")) for k, v in row.items()} for row in csv.DictReader(f)]


def listed(option: str, default, kind=float):
    """The comma-separated values after ``option`` on the command line, or ``default``."""
    if option not in sys.argv:
        return default
    return tuple(kind(v) for v in sys.argv[sys.argv.index(option) + 1].split(","))


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    ergun_rows, fluidized_rows = read_csv("suspensions_ergun.csv"), read_csv("suspensions_fluidized.csv")
    if "--plot" in sys.argv:       # the tables and the figure again from the CSVs (parts run apart)
        write_csv(OUT / "suspensions_minimum_fluidization.csv", minimum_fluidization(ergun_rows))
        return plot(ergun_rows, fluidized_rows)
    if "--fluidized" not in sys.argv:
        ergun_rows = ergun(listed("--cells", (3, 4, 6), int), listed("--reynolds", REYNOLDS),
                           listed("--corrections", CORRECTIONS, str))
        write_csv(OUT / "suspensions_minimum_fluidization.csv", minimum_fluidization(ergun_rows))
    if "--ergun" not in sys.argv:
        fluidized_rows = fluidized(listed("--speeds", FLUIDIZING), listed("--corrections", CORRECTIONS, str),
                                   listed("--dt", (1e-3,))[0])
    plot(ergun_rows, fluidized_rows)


if __name__ == "__main__":
    main()
