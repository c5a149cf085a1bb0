"""Checks before a run (pmpm/checks.py, and the output folder of pmpm/io.py): what cannot run is
refused with exit 2 and one line, what is suspicious is warned about, nothing is moved that is not
pmpm's own. In-process on 1 rank (``pmpm.__main__.main``), and a few through ``mpirun -n 2``."""
import io
import shutil
import subprocess
from contextlib import redirect_stderr, redirect_stdout

import pytest
from mpi4py import MPI

from conftest import mpirun_command, subprocess_env
from pmpm import checks
from pmpm.__main__ import main
from pmpm.errors import CaseError
from pmpm.io import prepare_output_folder
from test_cli import make_case, run_pmpm

# a 0.1 m box of 4³ cells with a flow: boundaries are added by the tests
FLOW = """
[run]
end_time = 0.02
dt = 0.005
[mesh]
box = { lower = [0, 0, 0], upper = [0.1, 0.1, 0.1], cells = [4, 4, 4] }
[fluid]
density = 1000.0
viscosity = 0.01
"""
# particles only, no [collisions]
BALLS = """
[run]
end_time = 0.02
dt = 0.005
[mesh]
box = { lower = [0, 0, 0], upper = [0.1, 0.1, 0.1], cells = [4, 4, 4] }
[[particles.add]]
position = [0.05, 0.05, 0.05]
radius = 0.01
density = 1000.0
"""


def run_in_process(*args):
    """``pmpm ARGS`` on this process's rank (1 under plain pytest): (status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        status = main([str(a) for a in args])
    return status, out.getvalue(), err.getvalue()


def refused(result, *fragments):
    """Exit 2, one line on stderr holding every fragment, no traceback."""
    status, out, err = result
    lines = [line for line in err.splitlines() if line.strip()]
    assert status == 2, err
    assert len(lines) == 1, err
    assert lines[0].startswith("pmpm: error: ") and "Traceback" not in err + out
    for fragment in fragments:
        assert fragment in lines[0]
    return lines[0]


def accepted(result):
    status, out, err = result
    assert status == 0, err
    assert "Traceback" not in err + out
    return out, err


# -- item 2: the output folder ------------------------------------------------------------------
def results_folder(folder, *extra):
    folder.mkdir()
    for name in ("particles.csv", "fields.h5", "summary.json", "checkpoint.h5") + extra:
        (folder / name).write_text(name)
    return folder


def test_output_folder_of_earlier_results_is_kept_by_renaming(tmp_path):
    folder = results_folder(tmp_path / "output")
    moved = prepare_output_folder(MPI.COMM_SELF, folder)
    assert moved == tmp_path / "output.1" and (moved / "particles.csv").read_text() == "particles.csv"
    assert folder.is_dir() and not any(folder.iterdir())


@pytest.mark.parametrize("other", ["case.toml", "notes.txt", "mesh"])
def test_output_folder_holding_anything_else_is_refused_and_left_alone(tmp_path, other):
    folder = results_folder(tmp_path / "output")
    (folder / other).mkdir() if other == "mesh" else (folder / other).write_text("mine")
    with pytest.raises(CaseError, match=rf"holds other things than pmpm's results \({other}\)"):
        prepare_output_folder(MPI.COMM_SELF, folder)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["output"]
    assert (folder / other).exists() and (folder / "particles.csv").exists()


def test_current_folder_with_results_is_not_renamed(tmp_path, monkeypatch):
    folder = results_folder(tmp_path / "run")
    monkeypatch.chdir(folder)
    with pytest.raises(CaseError, match="is the current folder"):
        prepare_output_folder(MPI.COMM_SELF, folder)
    assert (folder / "particles.csv").exists() and not (tmp_path / "run.1").exists()


def test_output_into_the_case_folder_is_refused_twice_on_two_ranks(tmp_path):
    """`--output .` from the case folder, and --output naming it: refused, nothing moved, twice."""
    folder = tmp_path / "case"
    folder.mkdir()
    make_case(folder)
    (folder / "notes.txt").write_text("my notes")
    for _ in range(2):
        command = mpirun_command(2) + ["-m", "pmpm", "case.toml", "--quiet", "--output", "."]
        result = subprocess.run(command, capture_output=True, text=True, timeout=120, env=subprocess_env(), cwd=folder)
        refused((result.returncode, result.stdout, result.stderr), "holds other things than pmpm's results",
                "case.toml")
    refused(run_in_process(folder, "--quiet", "--output", folder), "case.toml, notes.txt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["case"]
    assert sorted(p.name for p in folder.iterdir()) == ["case.toml", "notes.txt"]


# -- item 8: leftovers of an interrupted run ----------------------------------------------------
def test_partial_checkpoint_of_a_killed_run_is_removed_and_the_checkpoint_kept(tmp_path, capsys):
    folder = results_folder(tmp_path / "output", "checkpoint.h5.tmp", "summary.json.tmp")
    moved = prepare_output_folder(MPI.COMM_SELF, folder)
    assert sorted(p.name for p in moved.iterdir()) == ["checkpoint.h5", "fields.h5", "particles.csv", "summary.json"]
    assert (moved / "checkpoint.h5").read_text() == "checkpoint.h5"
    assert "removed" in capsys.readouterr().out and "checkpoint.h5.tmp" not in str(list(folder.iterdir()))


# -- item 3: boundaries -------------------------------------------------------------------------
def test_inlet_into_a_closed_box_is_refused(tmp_path):
    case = make_case(tmp_path, FLOW + '[boundary.xmin]\ntype = "inlet"\nvelocity = [0.5, 0, 0]\n')
    line = refused(run_in_process(case, "--check"), "no outlet", "xmin (inlet) +0.005 m³/s", 'type = "outlet"')
    assert "[boundary" in line


def test_balanced_inlets_in_a_closed_box_and_an_inlet_with_an_outlet_run(tmp_path):
    balanced = FLOW + ('[boundary.xmin]\ntype = "inlet"\nvelocity = [0.5, 0, 0]\n'
                       '[boundary.xmax]\ntype = "inlet"\nvelocity = [0.5, 0, 0]\n')
    out, err = accepted(run_in_process(make_case(tmp_path, balanced), "--check"))
    assert "warning" not in err
    with_outlet = FLOW + '[boundary.xmin]\ntype = "inlet"\nvelocity = [0.5, 0, 0]\n[boundary.xmax]\ntype = "outlet"\n'
    accepted(run_in_process(make_case(tmp_path, with_outlet), "--check"))


@pytest.mark.parametrize("motion", ['velocity = [0, 0, -0.1]', 'velocity = [0.1, 0, 0.1]',
                                    'angular_velocity = [1, 0, 0]\ncenter = [0, 0.05, 0.05]'])
def test_wall_moving_through_itself_is_refused(tmp_path, motion):
    case = make_case(tmp_path, FLOW + f"[boundary.zmax]\n{motion}\n")
    refused(run_in_process(case, "--check"), "[boundary.zmax]", "through the wall", "slide along itself")


@pytest.mark.parametrize("motion", ['velocity = [0.1, 0.05, 0]', 'angular_velocity = [0, 0, 2]\ncenter = [0.05, 0.05, 0]'])
def test_wall_sliding_along_itself_runs_without_warning(tmp_path, motion):
    out, err = accepted(run_in_process(make_case(tmp_path, FLOW + f"[boundary.zmax]\n{motion}\n"), "--check"))
    assert "warning" not in err


def test_suspicious_boundaries_are_warned_about(tmp_path):
    text = FLOW + ('[boundary.xmin]\ntype = "inlet"\nvelocity = [0, 0.5, 0]\n[boundary.xmax]\ntype = "outlet"\n'
                   'velocity = [1, 0, 0]\n')
    out, err = accepted(run_in_process(make_case(tmp_path, text), "--check"))
    assert "[boundary.xmin] inlet velocity = [0.0, 0.5, 0.0] carries no flow" in err
    assert '[boundary.xmax] velocity: ignored on a boundary of type "outlet"' in err


# -- item 5: tracebacks that became exit 2 ------------------------------------------------------
def test_box_of_1e15_cells_is_refused_before_building(tmp_path, monkeypatch):
    case = make_case(tmp_path, FLOW)
    line = refused(run_in_process(case, "--check", "--set", "mesh.box.cells=[100000,100000,100000]"),
                   "[mesh.box] cells = [100000, 100000, 100000]: 1e+15 hexahedra need ≈ 2.3 EB of memory",
                   "which has")
    assert "B free)" in line
    # a machine that could hold them: PETSc's 32-bit indices cannot number them
    monkeypatch.setattr(checks, "machine_memory", lambda: (10 ** 19, 10 ** 19))
    refused(run_in_process(case, "--check", "--set", "mesh.box.cells=[100000,100000,100000]"),
            "1e+15 hexahedra, more than the 2.68e+08 that PETSc's 32-bit indices can number")


def test_box_beyond_this_machines_memory_is_refused_with_the_estimate(tmp_path, monkeypatch):
    monkeypatch.setattr(checks, "machine_memory", lambda: (8 * 10 ** 9, 4 * 10 ** 9))
    case = make_case(tmp_path, FLOW)
    refused(run_in_process(case, "--check", "--set", "mesh.box.cells=[400,400,100]"),
            "1.6e+07 hexahedra need ≈ 36.9 GB of memory", "which has 8 GB (4 GB free)")
    # above what is free now but within the machine: a warning, and the run goes on
    monkeypatch.setattr(checks, "machine_memory", lambda: (8 * 10 ** 9, 10 ** 8))
    out, err = accepted(run_in_process(case, "--check"))
    assert "more than the 100 MB free now" in err


@pytest.mark.parametrize("option, message", [
    (("-pressure_ksp_type", "nonsense"), "-pressure_ksp_type nonsense: Unable to find requested KSP type nonsense"),
    (("-momentum_pc_type", "jacobbi"), '-momentum_pc_type jacobbi: Unable to find requested PC type jacobbi (did you mean "jacobi"?)'),
    (("-pressure_ksp_norm_type", "foo"), "Unknown option foo for -pressure_ksp_norm_type"),
])
def test_petsc_option_petsc_cannot_take_is_refused_naming_it(option, message):
    from petsc4py import PETSc
    options = PETSc.Options()
    options.setValue(option[0][1:], option[1])
    try:
        with pytest.raises(CaseError) as error:
            checks.check_petsc_options(MPI.COMM_SELF)
    finally:
        options.delValue(option[0][1:])
    assert message in str(error.value) and "\n" not in str(error.value)


def test_petsc_options_under_no_solver_prefix_are_warned_about(capsys):
    from petsc4py import PETSc
    options = PETSc.Options()
    options.setValue("ksp_monitor", "")
    try:
        checks.check_petsc_options(MPI.COMM_SELF)
    finally:
        options.delValue("ksp_monitor")
    assert "PETSc option -ksp_monitor: no pmpm solver reads it" in capsys.readouterr().err


# -- item 6: silently accepted ------------------------------------------------------------------
def test_sphere_larger_than_the_domain_is_refused_without_collisions(tmp_path):
    case = make_case(tmp_path, BALLS.replace("radius = 0.01", "radius = 0.5"))
    refused(run_in_process(case, "--check"), "particle 0: radius 0.5 m", "does not fit in the domain (0.1 × 0.1 × 0.1 m)")


INJECTION = """
[[injection]]
kind = "{kind}"
interval = 0.005
radius = 0.005
density = 1000.0
{where}
"""


@pytest.mark.parametrize("kind, where", [
    ("point", "position = [0.5, 0.05, 0.05]"),
    ("random", "lower = [0.2, 0, 0]\nupper = [0.3, 0.1, 0.1]"),
    ("cylindrical", "origin = [0.05, 0.05, 0.05]\nr = 0.2"),
    ("point", "position = [0.05, 0.05, 0.05]\nlocation_velocity = [100, 0, 0]\nstart = 0.005"),
])
def test_injection_releasing_only_outside_the_domain_is_refused(tmp_path, kind, where):
    case = make_case(tmp_path, BALLS + INJECTION.format(kind=kind, where=where))
    refused(run_in_process(case, "--check"), f"[[injection]] #0 ({kind})", "outside the domain",
            "nothing would be released")


def test_injection_partly_outside_or_too_late_is_warned_about(tmp_path):
    moving = INJECTION.format(kind="point", where="position = [0.05, 0.05, 0.05]\nlocation_velocity = [5, 0, 0]")
    late = INJECTION.format(kind="point", where="position = [0.05, 0.05, 0.05]\nstart = 1.0")
    out, err = accepted(run_in_process(make_case(tmp_path, BALLS + moving + late), "--check"))
    assert "[[injection]] #0: 40 % of the release points sampled lie outside the domain" in err
    assert "[[injection]] #1: no release before end_time = 0.02 s" in err


def test_restart_at_or_after_end_time_is_refused(tmp_path):
    case = make_case(tmp_path, BALLS.replace("dt = 0.005", "dt = 0.005\ncheckpoint_every = 0.01"))
    accepted(run_in_process(case, "--quiet", "--output", tmp_path / "first"))
    checkpoint = tmp_path / "first" / "checkpoint.h5"
    for end_time in ("0.02", "0.01"):
        refused(run_in_process(case, "--quiet", "--output", tmp_path / "again", "--restart", checkpoint,
                               "--set", f"run.end_time={end_time}"),
                f"--restart {checkpoint}: the checkpoint is at t = 0.02 s", "nothing to run")
    assert not (tmp_path / "again").exists()


def test_run_says_what_it_will_write_and_warns_on_a_huge_step_count(tmp_path):
    case = make_case(tmp_path, BALLS)
    out, err = accepted(run_in_process(case, "--check", "--set", "run.dt=2e-14"))
    assert "warning: [run] end_time = 0.02 s with dt = 2e-14 s is 1e+12 steps" in err
    writes = [line for line in out.splitlines() if line.strip().startswith("writes:")]
    assert len(writes) == 1 and "21 outputs (1 particle)" in writes[0] and "free" in writes[0]


def test_outputs_beyond_the_free_disk_are_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(checks.shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(10 ** 12, 10 ** 12 - 10 ** 5, 10 ** 5))
    case = make_case(tmp_path, BALLS)
    refused(run_in_process(case, "--check", "--set", "run.output_every=1e-6", "--set", "run.dt=1e-6"),
            "[run] output_every = 1e-06 s: 2e+04 outputs would write", "which has 100 kB free")
    out, _ = accepted(run_in_process(case, "--check"))   # one output a step: 5 of them fit in 100 kB
    assert "writes:    5 outputs (1 particle)" in out


# -- two ranks: refusals that involve every rank (agree, reductions, point location) -------------
CLI_REFUSALS = [
    ("petsc type", FLOW, ["-pressure_ksp_type", "nonsense"], "-pressure_ksp_type nonsense"),
    ("inlet, no outlet", FLOW + '[boundary.zmin]\ntype = "inlet"\nvelocity = [0, 0, 0.1]\n', [], "no outlet"),
    ("point injection outside", BALLS + INJECTION.format(kind="point", where="position = [0.05, 0.05, 0.5]"), [],
     "nothing would be released"),
]


@pytest.mark.parametrize("label, text, args, message", CLI_REFUSALS, ids=[c[0] for c in CLI_REFUSALS])
def test_refusals_on_two_ranks(tmp_path, label, text, args, message):
    result = run_pmpm([make_case(tmp_path, text), "--quiet", *args])
    line = refused((result.returncode, result.stdout, result.stderr), message)
    assert "[rank" not in line
    assert not (tmp_path / "output").exists()


def test_injection_into_a_closed_box_of_fluid_is_warned_about(tmp_path):
    """Particles injected into a fluid with no outlet displace fluid that cannot leave: the run
    says so before it starts (the mass source then spreads over the domain)."""
    text = FLOW + "[[injection]]\nposition = [0.05, 0.05, 0.05]\ninterval = 0.01\nradius = 0.005\ndensity = 2000.0\n"
    _, err = accepted(run_in_process(make_case(tmp_path, text), "--check"))
    assert "into a fluid with no outlet" in err
    with_outlet = text + "[boundary.zmax]\ntype = \"outlet\"\n"
    _, err = accepted(run_in_process(make_case(tmp_path, with_outlet), "--check"))
    assert "no outlet" not in err


# -- what a run says before it starts ----------------------------------------------------------
def test_a_run_says_when_it_compiles_the_contact_kernels_first(tmp_path, monkeypatch):
    """The contact kernels' cache counts as current only where its stamp is the digest of the
    compiled modules' sources (none in a fresh clone, another after an update): a run whose
    particles meet walls then says first that it compiles them; with the cache current, without
    walls, or with --check, it says nothing of it."""
    from pmpm.collisions import jit
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    folder = tmp_path / "__pycache__"
    assert not jit.cache_is_current(folder)
    folder.mkdir()
    (folder / "kernels.sha1").write_text("0" * 40)
    assert not jit.cache_is_current(folder)
    (folder / "kernels.sha1").write_text(jit.sources_digest())
    assert jit.cache_is_current(folder)
    # a run, with the package's cache taken as stale and then as current
    message = "pmpm: compiling the contact kernels first"
    (tmp_path / "walls").mkdir()
    (tmp_path / "balls").mkdir()
    walls = make_case(tmp_path / "walls", BALLS + "[collisions]\nrestitution = 0.5\n")
    no_walls = make_case(tmp_path / "balls", BALLS)
    monkeypatch.setattr(jit, "cache_is_current", lambda: False)
    out, _ = accepted(run_in_process(walls, "--quiet"))
    assert out.startswith(message)
    out, _ = accepted(run_in_process(no_walls, "--quiet"))
    assert message not in out
    out, _ = accepted(run_in_process(walls, "--check"))
    assert message not in out
    monkeypatch.setattr(jit, "cache_is_current", lambda: True)
    out, _ = accepted(run_in_process(walls, "--quiet", "--output", tmp_path / "again"))
    assert message not in out
