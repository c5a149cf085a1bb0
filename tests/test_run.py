"""The run as a batch job meets it: a flow that diverges stops the run with a state worth keeping,
and SIGTERM / SIGINT stop it cleanly with a checkpoint to continue from."""
import json
import signal
import subprocess
import time

import numpy as np
import pytest

from conftest import PYTHON, ROOT, mpirun_command, subprocess_env

CHANNEL = """
[run]
end_time = {end_time}
dt = {dt}
output_every = 0.1
[mesh]
box = {{ lower = [0, 0, 0], upper = [1.0, 0.1, 0.1], cells = [40, 4, 4] }}
[fluid]
density = 1000.0
viscosity = 1.0e-3
[boundary.xmin]
type = "inlet"
velocity = [5.0, 0.0, 0.0]
[boundary.xmax]
type = "outlet"
"""


def pmpm_command(folder, *options, ranks=1):
    return (mpirun_command(ranks) if ranks > 1 else [PYTHON]) + ["-m", "pmpm", str(folder), "--quiet", *options]


def channel(tmp_path, end_time=2.0, dt=0.004):
    (tmp_path / "case.toml").write_text(CHANNEL.format(end_time=end_time, dt=dt))
    return tmp_path


def test_a_diverging_flow_stops_with_a_good_state(tmp_path):
    """A 5 m/s channel at CFL 0.8 by its inlet speed: the flow speeds up to CFL ≈ 1.5 at the outlet
    and the explicit convection blows up (without the watch: NaN after 116 steps, with a "last
    good state" of kinetic energy 6e295 J). The run stops with exit 3 as soon as the CFL number
    passes 10, names the cell and a smaller dt, and writes a state whose speeds are of the
    order of the inlet's (kinetic energy within 10 × that of the whole channel at 5 m/s)."""
    folder = channel(tmp_path)
    result = subprocess.run(pmpm_command(folder), capture_output=True, text=True, timeout=300, env=subprocess_env())
    assert result.returncode == 3, result.stderr
    line = [text for text in result.stderr.splitlines() if "numerical failure" in text][0]
    assert "the flow is diverging: CFL number" in line and "in the cell at (" in line and "reduce [run] dt (to" in line
    summary = json.loads((folder / "output" / "summary.json").read_text())
    plug = 0.5 * 1000.0 * 1.0 * 0.1 * 0.1 * 5.0 ** 2
    assert summary["status"] == "numerical failure"
    assert 0 < summary["diagnostics"]["fluid_kinetic_energy"] < 10 * plug
    assert summary["diagnostics"]["final_cfl"] <= 2.0


def wait_for_progress(folder, process, seconds=120):
    """Until the run is in its time loop: its first output is written and it has taken a few steps."""
    deadline = time.time() + seconds
    while not (folder / "output" / "fields.xdmf").exists():
        assert process.poll() is None and time.time() < deadline, process.communicate()
        time.sleep(0.2)
    time.sleep(2.0)


@pytest.mark.parametrize("signal_number, ranks", [(signal.SIGTERM, 2), (signal.SIGINT, 1)])
def test_a_signal_stops_the_run_with_a_checkpoint(tmp_path, signal_number, ranks):
    """SIGTERM to every rank (as a batch scheduler sends it) or Ctrl-C's SIGINT: the run finishes
    its step, writes its outputs, a checkpoint and summary.json ("stopped by SIGTERM"), says so
    on stderr, and exits with 128 + the signal's number; a restart from the checkpoint goes on
    from the time it stopped at."""
    folder = channel(tmp_path, end_time=1000.0, dt=0.002)
    process = subprocess.Popen(pmpm_command(folder, ranks=ranks), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env=subprocess_env())
    wait_for_progress(folder, process)
    ranks_pids = [process.pid] if ranks == 1 else \
        [int(pid) for pid in subprocess.run(["pgrep", "-P", str(process.pid)], capture_output=True,
                                            text=True).stdout.split()]
    assert len(ranks_pids) == ranks
    for pid in ranks_pids:
        subprocess.run(["kill", f"-{signal_number}", str(pid)], check=True)
    _, stderr = process.communicate(timeout=120)
    name = signal.Signals(signal_number).name
    if ranks == 1:
        assert process.returncode == 128 + signal_number, stderr
    assert f"pmpm: stopped by {name} after step" in stderr and "Traceback" not in stderr, stderr
    summary = json.loads((folder / "output" / "summary.json").read_text())
    assert summary["status"] == f"stopped by {name}" and summary["steps"] > 0
    stopped_at = summary["simulated_time"]
    restart = subprocess.run(pmpm_command(folder, "--output", tmp_path / "more", "--set", f"run.end_time={stopped_at + 0.01}",
                                          "--restart", folder / "output" / "checkpoint.h5"),
                             capture_output=True, text=True, timeout=300, env=subprocess_env())
    assert restart.returncode == 0, restart.stderr
    more = json.loads((tmp_path / "more" / "summary.json").read_text())
    assert more["steps"] == summary["steps"] + 5 and more["simulated_time"] == pytest.approx(stopped_at + 0.01)
    assert np.isfinite(more["diagnostics"]["fluid_kinetic_energy"])


LATE_SIGNAL = """
import os, signal
from mpi4py import MPI
from pmpm.signals import StopRequests
before = signal.getsignal(signal.SIGTERM)
with StopRequests() as stops:   # a run that ends without a stop gives the handlers back
    assert stops.agreed(MPI.COMM_SELF) == (0, False)
assert signal.getsignal(signal.SIGTERM) is before
with StopRequests() as stops:   # this rank's own signal, or another rank's: the ranks stop together
    os.kill(os.getpid(), signal.SIGINT)
    assert stops.agreed(MPI.COMM_SELF) == (signal.SIGINT, False)
os.kill(os.getpid(), signal.SIGTERM)   # the SIGTERM sent to every rank reaches this one late
print("still writing the state")
"""


def test_a_signal_after_the_ranks_agreed_to_stop_is_ignored():
    """A scheduler's SIGTERM reaches the ranks at slightly different times: a rank may agree to
    stop on another's signal and receive its own while it writes the state. That one must not
    kill it (it did: mpirun then ended the job with no summary, half the time on 2 ranks)."""
    result = subprocess.run([PYTHON, "-c", LATE_SIGNAL], capture_output=True, text=True, timeout=60,
                            env=subprocess_env(), cwd=ROOT)
    assert result.returncode == 0 and "still writing the state" in result.stdout, result.stderr


SETTLING = """
[run]
end_time = 0.04
dt = 0.004
output_every = 0.02
checkpoint_every = 0.02
gravity = [0.3, 0.0, -9.81]
[mesh]
box = { lower = [0, 0, 0], upper = [0.06, 0.06, 0.1], cells = [10, 10, 16] }
[fluid]
density = 1000.0
viscosity = 0.1
[coupling]
volume_fraction = "subcell"
[[particles.add]]
position = [0.029, 0.031, 0.06]
radius = 0.008
density = 2000.0
"""


def test_two_rank_runs_repeat_and_restart_bit_for_bit(tmp_path):
    """The same case twice on 2 ranks writes the same particles.csv and fields.h5, bit for bit (the
    mesh is partitioned the same way every time), and a run restarted on 2 ranks from its
    checkpoint at half time ends bit for bit where the uninterrupted one ends."""
    import h5py
    (tmp_path / "case.toml").write_text(SETTLING)

    def run(name, *options):
        result = subprocess.run(pmpm_command(tmp_path, "--output", tmp_path / name, *options, ranks=2),
                                capture_output=True, text=True, timeout=300, env=subprocess_env())
        assert result.returncode == 0, result.stderr
        last = np.loadtxt(tmp_path / name / "particles.csv", delimiter=",", skiprows=1, ndmin=2)[-1]
        with h5py.File(tmp_path / name / "fields.h5", "r") as f:
            group = sorted(f["output"])[-1]
            return last, f[f"output/{group}/velocity"][...], f[f"output/{group}/pressure"][...]

    first, again = run("first"), run("again")
    run("half", "--set", "run.end_time=0.02")
    rest = run("rest", "--restart", tmp_path / "half" / "checkpoint.h5")
    assert first[0][0] == pytest.approx(0.04) and first[0][7] < -0.01, "the sphere settles"
    for other in (again, rest):
        for a, b in zip(first, other):
            np.testing.assert_array_equal(a, b)


def test_adaptive_time_step_keeps_the_flow_stable_and_outputs_on_time(tmp_path):
    """The channel with [run] dt = 0.05 s (CFL 10: it diverges at once, above) and adaptive_cfl =
    0.5: the run completes, every output lands on its requested time, and the last step's CFL
    number is at most the target (and not far below: the step lags behind by at most 25 % before
    it grows, and the last one may be halved to land on the end time)."""
    import h5py
    folder = channel(tmp_path, end_time=0.5, dt=0.05)
    result = subprocess.run(pmpm_command(folder, "--set", "run.adaptive_cfl=0.5"), capture_output=True, text=True,
                            timeout=300, env=subprocess_env())
    assert result.returncode == 0, result.stderr
    summary = json.loads((folder / "output" / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["simulated_time"] == pytest.approx(0.5, rel=1e-12)
    assert 0.5 / 1.25 / 2 <= summary["diagnostics"]["final_cfl"] <= 0.5 * 1.0001
    with h5py.File(folder / "output" / "fields.h5", "r") as f:
        times = [f[f"output/{group}"].attrs["time"] for group in sorted(f["output"])]
    np.testing.assert_allclose(times, np.arange(6) * 0.1, rtol=0, atol=1e-12)


def test_the_first_adaptive_step_of_a_flow_from_rest_stays_below_max_cfl(tmp_path):
    """The ventilated box: its first projection's flow meets 2.7 × the inlet speed at the outlet's
    edge, so a first step sized by the boundary speeds gave CFL 1.35 and a warning; the first step
    takes a quarter of that limit, and no step warns."""
    command = pmpm_command(ROOT / "cases" / "ventilated_box", "--output", str(tmp_path / "out"), "--set",
                           "run.end_time=0.005", "--set", "run.output_every=0.005")
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, env=subprocess_env())
    assert result.returncode == 0, result.stderr
    assert "CFL" not in result.stderr, result.stderr


BUG_ON_ONE_RANK = """
import sys
from mpi4py import MPI
import pmpm.simulation as simulation
original = simulation.move_particles
def broken(*args, **kwargs):
    if MPI.COMM_WORLD.rank == 1 and args[1].step == 3:
        raise ValueError("a bug on rank 1")
    return original(*args, **kwargs)
simulation.move_particles = broken
from pmpm.__main__ import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_bug_on_one_rank_takes_every_rank_down_without_hanging(tmp_path):
    """An exception that is not a user's mistake, raised on rank 1 alone in the middle of a run: the
    run did not hang (the summary, which is collective, used to be written on that rank while the
    other waited inside the step), every rank exits, non-zero, and the traceback names the bug."""
    folder = channel(tmp_path, end_time=0.2, dt=0.004)
    with open(folder / "case.toml", "a") as case:
        case.write("\n[[particles.add]]\nposition = [0.5, 0.05, 0.05]\nradius = 0.02\ndensity = 2000.0\n")
    (tmp_path / "broken.py").write_text(BUG_ON_ONE_RANK)
    command = mpirun_command(2) + [str(tmp_path / "broken.py"), str(folder), "--quiet"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120, env=subprocess_env())
    assert result.returncode != 0
    assert "a bug on rank 1" in result.stderr


CLOCK_AHEAD_ON_RANK_0 = """
import sys, time, types
from mpi4py import MPI
import pmpm.simulation as simulation
calls = []
def perf_counter():   # rank 0's clock jumps an hour ahead after a few steps; rank 1's does not
    calls.append(1)
    return time.perf_counter() + (3600.0 if MPI.COMM_WORLD.rank == 0 and len(calls) > 8 else 0.0)
simulation.wallclock = types.SimpleNamespace(perf_counter=perf_counter)
from pmpm.__main__ import main
sys.exit(main(sys.argv[1:]))
"""


def test_the_ranks_stop_together_at_the_wall_time_limit(tmp_path):
    """Each rank reads its own clock: one past [run] wall_time_limit while another is not yet used
    to stop alone and leave the other waiting in the next step. Rank 0 is made an hour ahead: both
    ranks stop after the same step, with the summary's status, and the run is not complete."""
    folder = channel(tmp_path, end_time=0.4, dt=0.004)
    text = (folder / "case.toml").read_text().replace("output_every = 0.1", "output_every = 0.1\nwall_time_limit = 600.0")
    (folder / "case.toml").write_text(text)
    (tmp_path / "ahead.py").write_text(CLOCK_AHEAD_ON_RANK_0)
    command = mpirun_command(2) + [str(tmp_path / "ahead.py"), str(folder), "--quiet"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120, env=subprocess_env())
    assert result.returncode == 0, result.stderr
    summary = json.loads((folder / "output" / "summary.json").read_text())
    assert summary["status"] == "stopped at the wall-time limit"
    assert 0 < summary["steps"] < 100


def test_the_eta_follows_the_recent_pace_not_the_first_steps(monkeypatch, capsys):
    """Progress lines: a first step that took 40 s (kernels compiling), then 1/64 s a step, a line
    every 5 s: the first line, after that one step, gives no ETA; every later one 1/64 s for each
    step left (the mean pace since the start would add up to 40 s); the last says 0."""
    from mpi4py import MPI
    from pmpm import reporting

    clock = [0.0]
    monkeypatch.setattr(reporting.wallclock, "perf_counter", lambda: clock[0])
    progress = reporting.Progress(MPI.COMM_SELF, end_time=1000 / 1024, quiet=False)
    for step in range(1, 1001):   # (times exact in binary)
        clock[0] += 40.0 if step == 1 else 1 / 64
        progress.update(step, step / 1024, force=step == 1000)
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("step")]
    eta = [line.split("ETA")[1].split()[0] for line in lines]
    steps = [int(line.split()[1]) for line in lines]
    assert steps == [1, 321, 641, 961, 1000] and eta[0] == "?"
    assert [float(value) for value in eta[1:]] == [pytest.approx((1000 - s) / 64, abs=0.05) for s in steps[1:]]
    assert steps[-1] == 1000 and float(eta[-1]) == 0.0
