"""The contact engine's speed, printed in one run (docs/collisions.md):

    OMP_NUM_THREADS=1 .venv/bin/python bench/contacts.py [--baseline DIR] [--skip-case] [--big N] [--big-ranks R]
                                                        [--big-only]

1. ``cases/bouncing_balls`` as shipped, on 2 ranks, the whole command (``mpirun -n 2 python -m pmpm``,
   start-up and output included): wall seconds and the run's stage times. With ``--baseline DIR``
   the same command is timed first on another checkout of pmpm (e.g. an older commit: ``git
   worktree add /tmp/old <commit>``), run from DIR so that ``python -m pmpm`` imports that one.
2. Time per step against the number of contacts: beds at rest (dense steps and, below the dense
   threshold, resting solves), a gas of spheres in flight (impacts in time order) and a bed
   settling (dense steps while it packs), each stepped by ``advance_with_collisions`` directly
   (no mesh, no flow): ms per step after the first steps, contacts and sweeps per step.
3. A DEM bed of N spheres (default 100,000) settling on 1 rank: ms per step and the memory a step
   allocates at its peak, per particle (tracemalloc: numpy's arrays included), short; with
   ``--big-ranks R``, the same bed on R ranks owning their particles (``mpirun -n R``,
   ``collisions.subdomains.advance_owned``): ms per step (the slowest rank's), owned and ghost
   particles per rank, and the bytes each rank sends per step, per owned particle.
4. Rest and overlaps (``bench/contact_rest.py``, on this checkout and the baseline): a bed in
   equilibrium and a poured one (largest speed and spin about the vertical once settled), a
   sphere released into a wall (the speed it gets, the time the step takes).

Timings on a shared machine are noisy: the load average is printed with each part.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from pmpm.collisions import CollisionSettings, Walls, advance_with_collisions  # noqa: E402
from pmpm.particles import ParticleState  # noqa: E402

G = 9.81


def load() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def box(side, height, **coefficients) -> Walls:
    """An open box [0, side]² × [0, height]: floor and four sides, two triangles each."""
    o = np.zeros(3)
    faces = [(o, (side, 0, 0), (0, side, 0)), (o, (0, 0, height), (side, 0, 0)),
             ((0, side, 0), (side, 0, 0), (0, 0, height)), (o, (0, side, 0), (0, 0, height)),
             ((side, 0, 0), (0, 0, height), (0, side, 0))]
    triangles = []
    for origin, e1, e2 in faces:
        p, e1, e2 = np.asarray(origin, float), np.asarray(e1, float), np.asarray(e2, float)
        triangles += [[p, p + e1, p + e1 + e2], [p, p + e1 + e2, p + e2]]
    return Walls.from_triangles(triangles, **coefficients)


def spheres(x, v, radius, density=2500.0) -> ParticleState:
    n = len(x)
    return ParticleState.empty().appended(np.arange(n), x, v, np.zeros((n, 3)), np.full(n, radius), np.full(n, density),
                                          np.zeros(n, np.int8))


def pyramid_bed(r, k, layers=3):
    """k × k touching spheres on the floor and layers in the pockets above: a packing at rest."""
    rows = []
    for level in range(layers):
        offset = r if level % 2 == 0 else 2 * r
        count = k if level % 2 == 0 else k - 1
        grid = offset + 2 * r * np.arange(count)
        rows += [[a, b, r + level * r * np.sqrt(2)] for a in grid for b in grid]
    return np.array(rows), 2 * r * k


def run_case(command, cwd, env) -> tuple[float, dict]:
    start = time.perf_counter()
    result = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{result.stderr[-2000:]}")
    return seconds, result


def bouncing_balls(baseline: str | None) -> None:
    runs = ([("baseline " + baseline, Path(baseline))] if baseline else []) + [("this checkout", ROOT)]
    for label, tree in runs:
        with tempfile.TemporaryDirectory(prefix="pmpm_bench_bb_") as name:
            bouncing_balls_run(label, tree, Path(name))


def bouncing_balls_run(label: str, tree: Path, out: Path) -> None:
    """``cases/bouncing_balls`` on 2 ranks from the checkout ``tree``, its outputs in ``out``: prints the
    whole command's seconds and the stages'."""
    flags = ["--oversubscribe", "--quiet"] + (["--allow-run-as-root"] if os.geteuid() == 0 else [])
    python = str(ROOT / ".venv" / "bin" / "python")
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if tree != ROOT:  # that checkout's pmpm, without writing into it
        env.update(PYTHONPATH=str(tree), PYTHONDONTWRITEBYTECODE="1",
                   NUMBA_CACHE_DIR=str(Path(tempfile.gettempdir()) / "pmpm_bench_numba_baseline"))
    command = ["mpirun", *flags, "-n", "2", python, "-m", "pmpm", str(tree / "cases" / "bouncing_balls"),
               "--quiet", "--output", str(out / "warm-up")]
    run_case(command + ["--set", "run.end_time=0.002"], tree, env)  # compiled kernels cached, files warm
    command[-1] = str(out / "run")
    seconds, _ = run_case(command, tree, env)
    summary = json.loads((out / "run" / "summary.json").read_text())
    stages = ", ".join(f"{k} {v:.1f}" for k, v in summary["wall_seconds"].items())
    print(f"bouncing_balls 2 ranks ({label}): whole command {seconds:.1f} s; stages (rank 0, s): {stages}; "
          f"{load()}", flush=True)


def stepping(state, walls, settings, dt, steps, gravity=(0.0, 0.0, -G), skip=5):
    """ms per step (after ``skip`` steps), and per step: contacts searched, acting, sweeps."""
    memory, seconds, counts = None, 0.0, np.zeros(3)
    for k in range(steps):
        state.v[state.movable] += np.asarray(gravity) * dt
        start = time.perf_counter()
        result = advance_with_collisions(state, walls, dt, settings, memory)
        elapsed = time.perf_counter() - start
        memory, walls = result.memory, result.walls
        if k >= skip:
            seconds += elapsed
            s = result.stats
            counts += (s["contacts"], s["dense_contacts"] or s["resting_contacts"] + s["events"], s["sweeps"])
    n = steps - skip
    return 1000 * seconds / n, counts / n


def contacts_table() -> None:
    print(f"time per step against contacts ({load()}):")
    print(f"{'scene':44s} {'spheres':>8s} {'contacts':>9s} {'acting':>8s} {'sweeps':>7s} {'ms/step':>8s} "
          f"{'us/contact':>10s}")
    r, dt = 0.005, 1e-3
    rest = CollisionSettings(restitution=0.5, friction=0.5, rest_speed=3 * G * dt)
    rows = []
    for k in (5, 10, 20, 40, 80):
        x, side = pyramid_bed(r, k)
        rows.append((f"bed at rest, {k}x{k} base, dense steps", spheres(x, np.zeros_like(x), r),
                     box(side, 1.0, restitution=0.5, friction=0.5), rest, (0, 0, -G)))
    for k in (5, 8):
        x, side = pyramid_bed(r, k)
        events = CollisionSettings(restitution=0.5, friction=0.5, rest_speed=3 * G * dt, dense_contacts=0)
        rows.append((f"bed at rest, {k}x{k} base, resting solves", spheres(x, np.zeros_like(x), r),
                     box(side, 1.0, restitution=0.5, friction=0.5), events, (0, 0, -G)))
    rng = np.random.default_rng(0)
    for n in (1000, 10000):
        side = 2.2 * r * round(n ** (1 / 3)) * 2.0
        x = rng.uniform(r, side - r, (n, 3))
        x = x[np.argsort(x[:, 0])]
        rows.append((f"gas in flight, 1 m/s, {n} spheres", spheres(x, rng.normal(0, 0.6, (n, 3)), r),
                     box(side, side, restitution=1.0, friction=0.3),
                     CollisionSettings(restitution=1.0, friction=0.3, rest_speed=3 * G * dt), (0, 0, 0)))
    for k in (10, 30):
        g = r * 1.05 + 2.1 * r * np.arange(k)
        x = np.array([[a, b, c] for c in g for a in g for b in g])
        x += rng.uniform(-0.02 * r, 0.02 * r, x.shape)
        rows.append((f"bed settling from a loose lattice, {k}^3", spheres(x, np.zeros_like(x), r),
                     box(2.1 * r * k + r, 1.0, restitution=0.5, friction=0.5), rest, (0, 0, -G)))
    for label, state, walls, settings, gravity in rows:
        ms, (contacts, acting, sweeps) = stepping(state, walls, settings, dt, 40, gravity)
        print(f"{label:44s} {len(state):8d} {contacts:9.0f} {acting:8.0f} {sweeps:7.0f} {ms:8.2f} "
              f"{1000 * ms / max(contacts, 1):10.2f}", flush=True)


def bed_lattice(n: int):
    """n spheres on a jittered lattice 1 % apart over a box (state, walls, settings, dt)."""
    r, dt = 0.005, 1e-3
    k = int(np.ceil((n / 1.5) ** (1 / 3)))
    layers = int(np.ceil(n / k ** 2))
    g = r * 1.01 + 2.02 * r * np.arange(k)
    x = np.array([[a, b, r * 1.01 + 2.02 * r * c] for c in range(layers) for a in g for b in g])[:n]
    rng = np.random.default_rng(1)
    x += rng.uniform(-0.004 * r, 0.004 * r, x.shape)
    state = spheres(x, rng.normal(0, 0.01, x.shape), r)
    walls = box(2.02 * r * k + r, 10.0, restitution=0.5, friction=0.5)
    settings = CollisionSettings(restitution=0.5, friction=0.5, rest_speed=3 * G * dt)
    return state, walls, settings, dt


def big_bed(n: int) -> None:
    """n spheres on a jittered lattice 1 % apart falling into a box: a bed settling, timed once the
    layers have met (steps 20-39)."""
    state, walls, settings, dt = bed_lattice(n)
    memory, seconds, timed = None, 0.0, 0
    state_bytes = sum(getattr(state, f).nbytes for f in ("id", "x", "v", "omega", "radius", "density", "motion",
                                                         "deposited"))
    peak, contacts = 0, 0
    for step in range(40):
        state.v[state.movable] += np.array([0, 0, -G]) * dt
        tracemalloc.start()
        start = time.perf_counter()
        result = advance_with_collisions(state, walls, dt, settings, memory)
        elapsed = time.perf_counter() - start
        peak = max(peak, tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        memory, walls = result.memory, result.walls
        if step >= 20:
            seconds += elapsed
            timed += 1
            contacts = result.stats["contacts"]
    print(f"DEM bed settling, {n} spheres, 1 rank: {1000 * seconds / timed:.0f} ms per step (steps 20-39, "
          f"{contacts} contacts, {result.stats['dense_contacts']} acting, dense={result.stats['dense_steps']}); "
          f"state {state_bytes / n:.0f} B/particle, a step's peak allocation {peak / n:.0f} B/particle, contact "
          f"memory {sum(a.nbytes for a in memory.to_arrays().values()) / n:.0f} B/particle; {load()}", flush=True)


def big_bed_owned(n: int) -> None:
    """``big_bed`` on the ranks of this mpirun, each owning the particles in its box (bisected over
    the particles; particles migrate after each step): the slowest rank's ms per step (steps
    20-39), the largest owned and ghost counts, the bytes a rank sends per step per owned particle
    (ghosts, merges per sweep; migration not included), the state's bytes per owned particle."""
    from mpi4py import MPI
    from pmpm.collisions.subdomains import advance_owned
    from pmpm.ownership import bisect
    from pmpm.packed import exchanged, merged, packed
    from pmpm.state import RunState
    comm = MPI.COMM_WORLD
    state, walls, settings, dt = bed_lattice(n)
    partition = bisect(comm, state.x if comm.rank == 0 else np.zeros((0, 3)))
    state = RunState(0.0, 0, state, None, np.zeros((n, 3)), np.zeros((n, 3)), None, n, 0, ()).owned_by(
        comm.rank, partition).particles
    memory, seconds, timed, sent, ghosts, owned, contacts, clamps = None, 0.0, 0, 0.0, 0, 0, 0, 0
    for step in range(40):
        state.v[state.movable] += np.array([0, 0, -G]) * dt
        comm.Barrier()
        start = time.perf_counter()
        result = advance_owned(comm, partition, state, walls, dt, settings, memory)
        elapsed = comm.allreduce(time.perf_counter() - start, op=MPI.MAX)
        memory, walls = result.memory, result.walls
        owner = partition.owner_of(state.x)   # migration
        going = np.flatnonzero(owner != comm.rank)
        [(moved, _)] = exchanged(comm, (owner[going], packed(state, going)))
        state = merged(state, moved, owner == comm.rank)[0]
        if step >= 20:
            seconds += elapsed
            timed += 1
            sent += comm.allreduce(result.stats.get("exchanged_bytes", 0) / max(len(state), 1), op=MPI.MAX)
            clamps += result.stats["energy_clamps"]
            ghosts = max(ghosts, comm.allreduce(result.stats.get("ghosts", 0), op=MPI.MAX))
            owned = max(owned, comm.allreduce(result.stats.get("owned", len(state)), op=MPI.MAX))
            contacts = result.stats["dense_contacts"]
    state_bytes = sum(getattr(state, f).nbytes for f in ("id", "x", "v", "omega", "radius", "density", "motion",
                                                         "deposited"))
    if comm.rank == 0:
        print(f"DEM bed settling, {n} spheres, {comm.size} ranks: {1000 * seconds / timed:.0f} ms per step (steps "
              f"20-39, slowest rank; {contacts} contacts solved over the ranks, {result.stats['sweeps']} sweeps, "
              f"{clamps} energy clamps); per rank at most {owned} owned and {ghosts} ghosts; sent per step (mean, "
              f"the largest rank's) {sent / timed:.0f} B per owned particle; "
              f"state {state_bytes / max(len(state), 1):.0f} B/particle; {load()}", flush=True)


def rest_and_overlaps(baseline: str | None) -> None:
    python = str(ROOT / ".venv" / "bin" / "python")
    for label, tree in ([("baseline " + baseline, Path(baseline))] if baseline else []) + [("this checkout", ROOT)]:
        env = dict(os.environ, OMP_NUM_THREADS="1")
        if tree != ROOT:
            env.update(PYTHONPATH=str(tree), PYTHONDONTWRITEBYTECODE="1",
                       NUMBA_CACHE_DIR=str(Path(tempfile.gettempdir()) / "pmpm_bench_numba_baseline"))
        _, result = run_case([python, str(ROOT / "bench" / "contact_rest.py")], tree, env)
        print(f"rest and overlaps ({label}; {load()}):\n{result.stdout.rstrip()}", flush=True)


def main():
    options = sys.argv[1:]
    baseline = options[options.index("--baseline") + 1] if "--baseline" in options else None
    big = int(options[options.index("--big") + 1]) if "--big" in options else 100_000
    if "--big-only" in options:   # (under mpirun, from --big-ranks)
        big_bed_owned(big)
        return
    if "--skip-case" not in options:
        bouncing_balls(baseline)
    contacts_table()
    big_bed(big)
    if "--big-ranks" in options:
        ranks = options[options.index("--big-ranks") + 1]
        flags = ["--oversubscribe"] + (["--allow-run-as-root"] if os.geteuid() == 0 else [])
        subprocess.run(["mpirun", *flags, "-n", ranks, sys.executable, str(Path(__file__).resolve()), "--big-only",
                        "--big", str(big)], check=True, env=dict(os.environ, OMP_NUM_THREADS="1"))
    rest_and_overlaps(baseline)


if __name__ == "__main__":
    main()
