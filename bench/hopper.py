"""DEM-only hopper discharge (no flow), pmpm against LIGGGHTS on the same work.

    .venv/bin/python bench/hopper.py [N [SIM_TIME [DT]]]      # defaults: 10000 particles, 1.0 s, 2e-3 s

The peer's geometry and particles (../shared/peers/liggghts_hopper.sh): conical hopper, orifice
D0 = 30 mm, spheres d = 4 mm, ρ = 2500, restitution 0.9, friction 0.3. As the peer does, the
particles first settle with the orifice closed (untimed, once), then the timed discharge runs
SIM_TIME with the orifice open, on 1 and 2 ranks. Printed: wall time, particles discharged,
collisions per second, the discharge rate against Beverloo's law, and the time-to-solution ratio
against LIGGGHTS (Hertz contacts at dt = 2e-5 s) run by the peer script in the same invocation.
"""
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FILL_TIME = 0.6
PEER = ROOT.parent / "shared" / "peers" / "liggghts_hopper.sh"
sys.path.insert(0, str(ROOT / "tools"))
from hopper_mesh import DENSITY, DIAMETER, ORIFICE, hopper_mesh, particles  # noqa: E402

CASE = """
[run]
end_time = {end_time}
dt = {dt}
output_every = {end_time}
checkpoint_every = {end_time}
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


def pmpm(folder, ranks, restart=None, **values):
    (folder / "case.toml").write_text(CASE.format(**values))
    flags = ["--oversubscribe", "--quiet"] + (["--allow-run-as-root"] if os.geteuid() == 0 else [])
    command = ["mpirun", *flags, "-n", str(ranks), str(ROOT / ".venv/bin/python"), "-m", "pmpm", str(folder),
               "--quiet", "--output", str(folder / f"out{ranks}_{values['orifice']}")]
    if restart is not None:
        command += ["--restart", str(restart)]
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if result.returncode != 0:
        raise SystemExit(f"pmpm failed:\n{result.stderr}")
    out = folder / f"out{ranks}_{values['orifice']}"
    return seconds, json.loads((out / "summary.json").read_text()), out


def main():
    count = int(sys.argv[1]) if len(sys.argv) > 1 else 10000
    sim_time = float(sys.argv[2]) if len(sys.argv) > 2 else 1.0
    dt = float(sys.argv[3]) if len(sys.argv) > 3 else 2e-3
    import meshio
    folder = Path(tempfile.mkdtemp(prefix="pmpm_hopper_"))
    meshio.write(str(folder / "hopper.msh"), hopper_mesh(), file_format="gmsh22", binary=False)
    xyz = particles(count)
    table = np.column_stack([xyz, np.full(len(xyz), DIAMETER / 2), np.full(len(xyz), DENSITY)])
    np.savetxt(folder / "loose.txt", table, header="x y z radius density", comments="", fmt="%.6g")

    fill_seconds, fill, out = pmpm(folder, 1, end_time=FILL_TIME, dt=dt, orifice="wall", particles="loose.txt")
    print(f"fill: {count} particles settled for {FILL_TIME} s in {fill_seconds:.0f} s on 1 rank (untimed)", flush=True)
    checkpoint = out / "checkpoint.h5"

    bulk = 0.6 * DENSITY
    beverloo = 0.58 * bulk * np.sqrt(9.81) * (2 * ORIFICE - 1.5 * DIAMETER) ** 2.5   # kg/s
    beverloo_rate = beverloo / (DENSITY * np.pi * DIAMETER ** 3 / 6)
    results = {}
    for ranks in (1, 2):
        # the discharge continues the fill's checkpoint with the orifice open
        seconds, summary, _ = pmpm(folder, ranks, restart=checkpoint, end_time=FILL_TIME + sim_time, dt=dt,
                                   orifice="outlet", particles="loose.txt")
        collisions = summary["diagnostics"].get("collisions", {})
        events = collisions.get("particle_collisions", 0) + collisions.get("wall_collisions", 0)
        discharged = summary["particles_removed"]
        results[ranks] = seconds
        print(f"pmpm hopper ranks={ranks} particles={count} sim_time={sim_time} dt={dt} wall_s={seconds:.1f} "
              f"discharged={discharged} rate={discharged / sim_time:.0f}/s (Beverloo {beverloo_rate:.0f}/s) "
              f"collisions_per_wall_s={events / seconds:.0f}", flush=True)
    if results[1] and results[2]:
        print(f"pmpm speed-up 1 -> 2 ranks: {results[1] / results[2]:.2f}")
    if not PEER.exists():
        print(f"LIGGGHTS peer script not found at {PEER}: no comparison")
        return
    peer = subprocess.run(["bash", str(PEER), "--sim-time", str(sim_time), str(count)], capture_output=True, text=True)
    for line in peer.stdout.splitlines():
        match = re.search(r"ranks=(\d+).*wall_s=([0-9.]+).*discharged=(\d+)", line)
        if match:
            ranks, wall = int(match.group(1)), float(match.group(2))
            print(line)
            if ranks in results:
                print(f"  time-to-solution pmpm/LIGGGHTS on {ranks} rank(s): {results[ranks] / wall:.2f}")
    if peer.returncode != 0:
        print(f"LIGGGHTS peer failed (exit {peer.returncode}): {peer.stderr.strip()[-500:]}")


if __name__ == "__main__":
    main()
