"""How far one dense step's solve is from converged, on 1 and 2 ranks: the block Gauss–Seidel's
accuracy near the cut (docs/collisions.md, "Accuracy on several ranks").

    OMP_NUM_THREADS=1 .venv/bin/python bench/block_convergence.py [--sweeps 20,30,40] [--count 1500] [--keep]

The tests' small hopper (1,500 spheres, d = 4 mm, ``test_small_hopper_on_one_to_four_ranks``)
discharges for 0.3 s on 1 rank (ending in a checkpoint, which holds the contacts' impulses). From
it one step of 2 ms (a dense step) is taken: with 2000 sweeps on 1 rank (the reference), and with
each ``--sweeps`` budget (``collisions.dense_sweeps``) on 1 rank and on 2 ranks solving it by block
Gauss–Seidel (``gather_contacts = 0``). Printed per run: the RMS over the particles of
|v − v_ref| / RMS |v_ref| after the step, overall, within 2 d of the 2-rank cut (the bisection's:
the median of the longest horizontal extent) and beyond. One step from the same start is
deterministic, where discharge counts spread by ~3 % between runs that differ by round-off. The
runs' folder (in the system's temporary folder) is removed at the end; ``--keep`` keeps it and
prints where it is.
"""
import argparse
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT / "bench"))
from runs_folder import add_keep_option, runs_folder  # noqa: E402
START, DT, REFERENCE_SWEEPS = 0.3, 2e-3, 2000


def run(folder, ranks, label, settings, restart=None):
    """pmpm on ``folder``'s case with ``settings`` (KEY=VALUE overrides); the last output's particles by id."""
    flags = ["--oversubscribe", "--quiet"] + (["--allow-run-as-root"] if os.geteuid() == 0 else [])
    sets = [item for key in settings for item in ("--set", key)]
    command = ["mpirun", *flags, "-n", str(ranks), str(ROOT / ".venv/bin/python"), "-m", "pmpm", str(folder),
               "--quiet", "--output", str(folder / label), "--set", "collisions.gather_contacts=0", *sets]
    if restart is not None:
        command += ["--restart", str(restart)]
    result = subprocess.run(command, capture_output=True, text=True, env=dict(os.environ, OMP_NUM_THREADS="1"))
    if result.returncode != 0:
        raise SystemExit(f"pmpm failed:\n{result.stderr[-3000:]}")
    table = np.loadtxt(folder / label / "particles.csv", delimiter=",", skiprows=1)
    last = table[table[:, 0] == table[:, 0].max()]
    return last[np.argsort(last[:, 1])]   # time, id, x, y, z, vx, vy, vz, ...


def main():
    parser = argparse.ArgumentParser(description="one dense step's distance from converged, 1 and 2 ranks")
    parser.add_argument("--sweeps", default="20,30,40")
    parser.add_argument("--count", type=int, default=1500)
    add_keep_option(parser)
    args = parser.parse_args()
    with runs_folder("pmpm_block_", args.keep) as folder:   # every run's outputs
        convergence(folder, args)


def convergence(folder: Path, args) -> None:
    """The start, the reference step and one step per budget and rank count, in ``folder``; prints the errors."""
    import meshio
    from hopper import CASE
    from hopper_mesh import DENSITY, DIAMETER, hopper_mesh, particles
    budgets = [int(s) for s in args.sweeps.split(",")]
    meshio.write(str(folder / "hopper.msh"), hopper_mesh(), file_format="gmsh22", binary=False)
    xyz = particles(args.count)
    table = np.column_stack([xyz, np.full(len(xyz), DIAMETER / 2), np.full(len(xyz), DENSITY)])
    np.savetxt(folder / "p.txt", table, header="x y z radius density", comments="")
    (folder / "case.toml").write_text(CASE.format(end_time=START, dt=DT, output_every=START,
                                                  checkpoint=f"checkpoint_every = {START}", orifice="outlet",
                                                  particles="p.txt"))
    start = run(folder, 1, "start", [])
    restart = [f"run.end_time={START + DT}", f"run.output_every={DT}"]
    os.rename(folder / "start" / "checkpoint.h5", folder / "start.h5")

    def step(ranks, label, sweeps):
        return run(folder, ranks, label, restart + [f"collisions.dense_sweeps={sweeps}"], folder / "start.h5")

    reference = step(1, "reference", REFERENCE_SWEEPS)
    x, v_ref = reference[:, 2:5], reference[:, 5:8]
    scale = np.sqrt((v_ref ** 2).sum(1).mean())
    spread = start[:, 2:4].max(0) - start[:, 2:4].min(0)
    axis = int(np.argmax(spread))
    near = np.abs(x[:, axis] - np.median(start[:, 2 + axis])) < 2 * DIAMETER
    print(f"{len(reference)} particles at t = {START} s; one step of {DT} s; reference: {REFERENCE_SWEEPS} sweeps "
          f"on 1 rank; cut across {'xyz'[axis]}, {near.sum()} particles within 2 d of it")
    print(f"{'ranks':>5} {'sweeps':>6} {'all':>7} {'near cut':>9} {'beyond':>7}   (RMS |v - v_ref| / RMS |v_ref|)")
    for sweeps in budgets:
        for ranks in (1, 2):
            final = step(ranks, f"r{ranks}_s{sweeps}", sweeps)
            if not np.array_equal(final[:, 1], reference[:, 1]):
                raise SystemExit("the runs kept different particles")
            error = np.sqrt(((final[:, 5:8] - v_ref) ** 2).sum(1)) / scale
            rms = [np.sqrt((error[part] ** 2).mean()) for part in (slice(None), near, ~near)]
            print(f"{ranks:>5} {sweeps:>6} {rms[0]:>7.4f} {rms[1]:>9.4f} {rms[2]:>7.4f}", flush=True)


if __name__ == "__main__":
    main()
