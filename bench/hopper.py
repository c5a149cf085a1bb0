"""DEM-only hopper discharge (no flow), pmpm against LIGGGHTS on the same work.

    OMP_NUM_THREADS=1 .venv/bin/python bench/hopper.py [N [SIM_TIME [DT]]] [--ranks 1,2] [--repeat 3] [--no-peer]
                                                       [--one-core] [--keep]
    # defaults: 10000 particles, 1.0 s, 2e-3 s, 1 and 2 ranks, each timed 3 times, LIGGGHTS too

The peer's geometry and particles (../shared/peers/liggghts_hopper.sh): conical hopper, orifice D0 =
30 mm, spheres d = 4 mm, ρ = 2500, restitution 0.9, friction 0.3. As the peer does, the particles
first settle for 0.6 s with the orifice closed (untimed, once, 1 rank, ending in a checkpoint), then
the timed discharge restarts from that checkpoint with the orifice open and runs SIM_TIME, on 1 and
2 ranks (wall time of the whole process, start-up included, as the peer's wall_s), each rank count
``--repeat`` times, the rank counts taking turns (on a shared 2-core machine one run of the same
work varied by up to 40 % from one minute to the next): the speed-up and the ratios to the peer are
of the medians (the speed-up of the time loop alone, start-up and the end left out, beside it).
Printed per run: wall time, particles discharged, the steady discharge rate (second half of
SIM_TIME) against Beverloo's law (C = 0.58, k = 1.5, bulk density 0.6 ρ), collisions
(impacts faster than the rest speed) per wall second, events and dense-step contacts and sweeps per
step, and on several ranks the most particles a rank owned and held as ghosts and the most bytes it
sent in a contact step; then the LIGGGHTS peer (Hertz contacts at dt = 2e-5 s) run in the same
invocation, the time-to-solution ratio pmpm/LIGGGHTS and LIGGGHTS's own speed-up from 1 to 2 ranks
(what a second rank gains on this machine at that time: on a shared machine it moves by tens of per
cent from one day to the next, docs/collisions_log.md, "Sixteenth session"). Needs the peer's Debian package (liggghts),
which the peer script installs with apt-get if missing. On several ranks each rank owns the
particles in its box (docs/collisions.md, "Particles owned by ranks"); the fill and a 5-step untimed
discharge on each rank count compile the contact kernels (numba) once, the timed runs load them from
numba's cache (in a fresh clone, compiling inside the timed runs made them 11–14 s slower).
With ``--one-core`` the discharge is timed once more on each rank count with every rank on one core
(``taskset``; a waiting rank yields the core): its time loop is then the ranks' work added up, and
the ratio to one rank's says what several ranks do beyond one, apart from the waits that the
other core's stops cause (at most: on one core the ranks also switch at each exchange and refill
their caches; docs/collisions_log.md, "Twentieth session"); then ``bench/cpu_gaps.py --pace-only``
measures, for 20 s, what two cores in step lose to each other's slow spells on this machine in that
hour (docs/collisions.md, "Speed on 2 ranks"). The runs' folder (in the system's temporary folder, every
run's outputs) is removed at the end; ``--keep`` keeps it and prints where it is.
"""
import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FILL_TIME = 0.6
PEER = ROOT.parent / "shared" / "peers" / "liggghts_hopper.sh"
sys.path.insert(0, str(ROOT / "tools"))
from hopper_mesh import DENSITY, DIAMETER, ORIFICE, hopper_mesh, particles  # noqa: E402
from runs_folder import add_keep_option, runs_folder  # noqa: E402
from pmpm.reference import beverloo_mass_rate  # noqa: E402

CASE = """
[run]
end_time = {end_time}
dt = {dt}
output_every = {output_every}
{checkpoint}
gravity = [0.0, 0.0, -9.81]
[mesh]
file = "hopper.msh"
[boundary.orifice]
type = "{orifice}"
[particles]
file = "{particles}"
[collisions]
restitution = 0.9
friction = 0.3
"""


def pmpm(folder, ranks, restart=None, label="", one_core=False, **values):
    """Run pmpm on ``ranks`` ranks (with ``one_core``, every rank on core 0, a waiting rank yielding
    it: the wall time is then the ranks' work added up); returns the wall seconds, the summary and
    the output folder."""
    values.setdefault("output_every", values["end_time"])
    values.setdefault("checkpoint", "")
    (folder / "case.toml").write_text(CASE.format(**values))
    flags = ["--oversubscribe", "--quiet"] + (["--allow-run-as-root"] if os.geteuid() == 0 else [])
    pinned = []
    if one_core:
        pinned, flags = ["taskset", "-c", "0"], flags + ["--bind-to", "none", "--mca", "mpi_yield_when_idle", "1"]
    command = [*pinned, "mpirun", *flags, "-n", str(ranks), str(ROOT / ".venv/bin/python"), "-m", "pmpm", str(folder),
               "--quiet", "--output", str(folder / f"out{ranks}_{values['orifice']}{label}")]
    if restart is not None:
        command += ["--restart", str(restart)]
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if result.returncode != 0:
        raise SystemExit(f"pmpm failed:\n{result.stderr}")
    out = folder / f"out{ranks}_{values['orifice']}{label}"
    return seconds, json.loads((out / "summary.json").read_text()), out


def carries_counts(checkpoint) -> bool:
    """Whether a restart from ``checkpoint`` continues the run's collision counts."""
    import h5py
    with h5py.File(checkpoint, "r") as f:
        return "collisions" in f.attrs


def steady_rate(csv, start) -> float:
    """Particles leaving per second from the output time nearest ``start`` to the last one
    (Beverloo's law holds past the start-up of the discharge)."""
    times, counts = np.unique(np.loadtxt(csv, delimiter=",", skiprows=1, usecols=0), return_counts=True)
    first = int(np.argmin(np.abs(times - start)))
    if first >= len(times) - 1:
        return float("nan")
    return (counts[first] - counts[-1]) / (times[-1] - times[first])


def work_done(folder, rank_counts, repeat, discharge: dict) -> None:
    """The discharge's time loop with every rank on one core, the rank counts taking turns: its
    wall time is then the work of all ranks added up (their waits yield the core), so the ratio to
    one rank's is (at most) what several ranks do beyond one, whatever the other core's stops, and
    ranks × one rank's loop / that loop the (least) speed-up the ranks would reach with no waits."""
    loops = {ranks: [] for ranks in rank_counts}
    for ranks in turns(rank_counts, repeat):
        _, summary, _ = pmpm(folder, ranks, label="_one_core", one_core=True, **discharge)
        loops[ranks].append(summary["wall_seconds"]["total"])
    work = {ranks: float(np.median(times)) for ranks, times in loops.items()}
    for ranks, times in loops.items():
        against_one = ""
        if ranks > 1 and work.get(1):
            against_one = (f": the ranks' work {work[ranks] / work[1]:.2f} x one rank's, speed-up with no waits "
                           f"at least {ranks * work[1] / work[ranks]:.2f}")
        print(f"pmpm ranks={ranks} on one core: time loop median {work[ranks]:.1f} s "
              f"({', '.join(f'{t:.1f}' for t in times)}){against_one}")


def turns(rank_counts, repeat) -> list:
    """Each rank count ``repeat`` times, the rank counts taking turns (the machine's hour shared alike)."""
    return [ranks for _ in range(repeat) for ranks in rank_counts]


def main():
    parser = argparse.ArgumentParser(description="DEM hopper discharge, pmpm against LIGGGHTS")
    parser.add_argument("count", nargs="?", type=int, default=10000)
    parser.add_argument("sim_time", nargs="?", type=float, default=1.0)
    parser.add_argument("dt", nargs="?", type=float, default=2e-3)
    parser.add_argument("--ranks", default="1,2")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--no-peer", action="store_true")
    parser.add_argument("--one-core", action="store_true",
                        help="also time each rank count with every rank on one core: the work the ranks do")
    add_keep_option(parser)
    args = parser.parse_args()
    with runs_folder("pmpm_hopper_", args.keep) as folder:   # every run's outputs
        benchmark(folder, args)


def benchmark(folder: Path, args) -> None:
    """The fill, the timed discharges and the peer's, in ``folder``; prints the figures."""
    count, sim_time, dt, repeat = args.count, args.sim_time, args.dt, args.repeat
    rank_counts = [int(n) for n in args.ranks.split(",")]
    import meshio
    meshio.write(str(folder / "hopper.msh"), hopper_mesh(), file_format="gmsh22", binary=False)
    xyz = particles(count)
    table = np.column_stack([xyz, np.full(len(xyz), DIAMETER / 2), np.full(len(xyz), DENSITY)])
    np.savetxt(folder / "loose.txt", table, header="x y z radius density", comments="", fmt="%.6g")

    fill_seconds, fill, out = pmpm(folder, 1, end_time=FILL_TIME, dt=dt, orifice="wall", particles="loose.txt",
                                checkpoint=f"checkpoint_every = {FILL_TIME}")
    print(f"fill: {count} particles settled for {FILL_TIME} s in {fill_seconds:.0f} s on 1 rank (untimed)", flush=True)
    checkpoint = out / "checkpoint.h5"

    bulk = 0.6 * DENSITY
    beverloo = beverloo_mass_rate(2 * ORIFICE, DIAMETER, bulk)   # kg/s, C = 0.58, k = 1.5
    beverloo_rate = beverloo / (DENSITY * np.pi * DIAMETER ** 3 / 6)
    for ranks in rank_counts:   # untimed: kernels a rank count meets first (numba) compile here, not below
        pmpm(folder, ranks, restart=checkpoint, label="_warm", end_time=FILL_TIME + 5 * dt, dt=dt, orifice="outlet",
             particles="loose.txt", output_every=5 * dt)
    results = {ranks: [] for ranks in rank_counts}
    loops = {ranks: [] for ranks in rank_counts}   # the time loop alone (summary.json's total)
    # the discharge continues the fill's checkpoint with the orifice open
    discharge = dict(restart=checkpoint, end_time=FILL_TIME + sim_time, dt=dt, orifice="outlet", particles="loose.txt")
    for ranks in turns(rank_counts, repeat):
        seconds, summary, out = pmpm(folder, ranks, output_every=sim_time / 10, **discharge)
        collisions = dict(summary["diagnostics"].get("collisions", {}))
        if carries_counts(checkpoint):  # the discharge's counts then start from the fill's
            carried = fill["diagnostics"].get("collisions", {})
            collisions = {key: value - carried.get(key, 0) for key, value in collisions.items()}
        impacts = collisions.get("particle_collisions", 0) + collisions.get("wall_collisions", 0)
        steps = round(sim_time / dt)
        discharged = summary["particles_removed"] - fill.get("particles_removed", 0)  # the restart carries the fill's
        steady = steady_rate(out / "particles.csv", FILL_TIME + sim_time / 2)
        results[ranks].append(seconds)
        loops[ranks].append(summary["wall_seconds"]["total"])
        print(f"pmpm hopper ranks={ranks} run={len(results[ranks])} particles={count} sim_time={sim_time} dt={dt} "
              f"steps={steps} wall_s={seconds:.1f} collisions_s={summary['wall_seconds'].get('collisions', 0):.1f} "
              f"discharged={discharged} rate={discharged / sim_time:.0f}/s "
              f"steady_rate={steady:.0f}/s (Beverloo {beverloo_rate:.0f}/s, ratio {steady / beverloo_rate:.2f}) "
              f"collisions={impacts} collisions_per_wall_s={impacts / seconds:.0f} "
              f"events_per_step={collisions.get('events', 0) / steps:.1f} "
              f"dense_steps={collisions.get('dense_steps', 0)} "
              f"contacts_per_step={collisions.get('dense_contacts', 0) / steps:.0f} "
              f"resting_contacts_per_step={collisions.get('resting_contacts', 0) / steps:.0f} "
              f"sweeps_per_step={collisions.get('sweeps', 0) / steps:.1f} "
              f"energy_clamps={collisions.get('energy_clamps', 0)} capped_steps={collisions.get('capped', 0)}"
              + "".join(f" {key}={value}" for key, value in summary.get("particles_per_rank", {}).items())
              + f" load={os.getloadavg()[0]:.1f}", flush=True)
    for ranks, times in results.items():
        print(f"pmpm ranks={ranks}: median {np.median(times):.1f} s, fastest {min(times):.1f} s of {len(times)} "
              f"({', '.join(f'{t:.1f}' for t in times)})")
    results = {ranks: float(np.median(times)) for ranks, times in results.items()}
    if results.get(1) and results.get(2):
        loop = {ranks: float(np.median(times)) for ranks, times in loops.items()}
        print(f"pmpm speed-up 1 -> 2 ranks (medians): {results[1] / results[2]:.2f} "
              f"(the time loop alone: {loop[1]:.1f} / {loop[2]:.1f} s, {loop[1] / loop[2]:.2f})")
    if args.one_core:
        work_done(folder, rank_counts, repeat, discharge)
        # and the machine's share: what two cores in step lose to each other's slow spells, this hour
        pace = subprocess.run([sys.executable, str(ROOT / "bench" / "cpu_gaps.py"), "20", "--pace-only"],
                              capture_output=True, text=True)
        print(pace.stdout.strip() or f"bench/cpu_gaps.py failed: {pace.stderr.strip()[-300:]}")
    if args.no_peer:
        return
    if not PEER.exists():
        print(f"LIGGGHTS peer script not found at {PEER}: no comparison")
        return
    peer = subprocess.run(["bash", str(PEER), "--sim-time", str(sim_time), str(count)], capture_output=True, text=True)
    peer_walls = {}
    for line in peer.stdout.splitlines():
        match = re.search(r"ranks=(\d+).*wall_s=([0-9.]+).*discharged=(\d+)", line)
        if match:
            ranks, wall = int(match.group(1)), float(match.group(2))
            peer_walls[ranks] = wall
            print(line)
            if ranks in results:
                print(f"  time-to-solution pmpm/LIGGGHTS on {ranks} rank(s): {results[ranks] / wall:.2f} "
                      f"(LIGGGHTS discharged {match.group(3)} = {int(match.group(3)) / sim_time:.0f}/s)")
    if peer_walls.get(1) and peer_walls.get(2):   # what 2 ranks gain on this machine at this time, for another code
        print(f"LIGGGHTS speed-up 1 -> 2 ranks: {peer_walls[1] / peer_walls[2]:.2f}")
    if peer.returncode != 0:
        print(f"LIGGGHTS peer failed (exit {peer.returncode}): {peer.stderr.strip()[-500:]}")


if __name__ == "__main__":
    main()
