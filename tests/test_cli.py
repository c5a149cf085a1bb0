"""The command line on 2 ranks: every bad input of the README's list exits 2 with one line on stderr, no
traceback, no hang; results are never overwritten; --set and --check work."""
import json
import subprocess

import numpy as np
import pytest

from conftest import PYTHON, mpirun_command, subprocess_env

CASE = """
[run]
end_time = 0.02
dt = 0.005
output_every = 0.01
[mesh]
box = { lower = [0, 0, 0], upper = [0.1, 0.1, 0.1], cells = [4, 4, 4] }
[[particles.add]]
position = [0.05, 0.05, 0.05]
velocity = [0.1, 0.0, 0.0]
radius = 0.01
density = 1000.0
[[particles.add]]
position = [0.02, 0.02, 0.08]
radius = 0.01
density = 1000.0
[collisions]
"""


def run_pmpm(args, ranks=2, timeout=60):
    command = (mpirun_command(ranks) if ranks > 1 else [PYTHON]) + ["-m", "pmpm", *map(str, args)]
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=subprocess_env())


def make_case(tmp_path, text=CASE, extra_files=()):
    (tmp_path / "case.toml").write_text(text)
    for name, content in extra_files:
        (tmp_path / name).write_text(content)
    return tmp_path


BAD_INPUTS = [
    ("unknown key", ("radius = 0.01", "radus = 0.01"), 'unknown key "radus" (did you mean "radius"?)'),
    ("unknown section", ("[collisions]", "[colisions]"), 'unknown section [colisions] (did you mean "collisions"?)'),
    ("wrong type", ("end_time = 0.02", 'end_time = "soon"'), "[run] end_time = \"soon\": must be a number"),
    ("zero radius", ("radius = 0.01", "radius = 0.0"), "radius = 0.0: must be > 0"),
    ("negative density", ("density = 1000.0", "density = -1.0"), "density = -1.0: must be > 0"),
    ("zero viscosity", ("[collisions]", "[collisions]\n[fluid]\ndensity = 1.0\nviscosity = 0.0"), "viscosity = 0.0: must be > 0"),
    ("dt <= 0", ("dt = 0.005", "dt = -0.005"), "[run] dt = -0.005: must be > 0"),
    ("end time <= 0", ("end_time = 0.02", "end_time = 0.0"), "[run] end_time = 0.0: must be > 0"),
    ("outside the domain", ("position = [0.05, 0.05, 0.05]", "position = [0.5, 0.05, 0.05]"), "outside the domain"),
    ("overlapping particles", ("position = [0.02, 0.02, 0.08]", "position = [0.055, 0.05, 0.05]"), "overlap"),
    ("overlapping a wall", ("position = [0.02, 0.02, 0.08]", "position = [0.005, 0.05, 0.05]"), "wall"),
    ("missing mesh file", ("box = { lower = [0, 0, 0], upper = [0.1, 0.1, 0.1], cells = [4, 4, 4] }", 'file = "nope.msh"'), "nope.msh"),
    ("missing particle file", ("[collisions]", "[collisions]\n[particles]\nfile = \"nope.txt\""), "nope.txt"),
    # read by rank 0 alone while the mesh is partitioned (its work shared): every rank must leave
    ("missing particle file in a flow", ("[collisions]", "[collisions]\n[fluid]\ndensity = 1.0\nviscosity = 1e-3\n"
                                         "[particles]\nfile = \"nope.txt\""), "nope.txt"),
    ("unknown boundary", ("[collisions]", "[collisions]\n[boundary.inlet]\ntype = \"wall\""), 'no boundary "inlet"'),
]


@pytest.mark.parametrize("label, change, message", BAD_INPUTS, ids=[b[0] for b in BAD_INPUTS])
def test_bad_input_exits_2_on_two_ranks(tmp_path, label, change, message):
    text = CASE.replace(*change, 1)
    assert text != CASE
    result = run_pmpm([make_case(tmp_path, text), "--quiet"])
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert message in lines[0]
    assert "Traceback" not in result.stderr + result.stdout


def test_mesh_file_that_is_not_a_mesh(tmp_path):
    text = CASE.replace("box = { lower = [0, 0, 0], upper = [0.1, 0.1, 0.1], cells = [4, 4, 4] }", 'file = "mesh.msh"')
    folder = make_case(tmp_path, text, [("mesh.msh", "this is not a mesh\n")])
    result = run_pmpm([folder, "--quiet"])
    assert result.returncode == 2, result.stderr
    assert "not a mesh" in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_unknown_set_key_and_bad_option(tmp_path):
    folder = make_case(tmp_path)
    result = run_pmpm([folder, "--set", "run.dtt=0.1"])
    assert result.returncode == 2 and 'did you mean "dt"' in result.stderr
    result = run_pmpm([folder, "--frobnicate"])
    assert result.returncode == 2 and "unrecognized arguments" in result.stderr


def test_check_set_and_results_kept(tmp_path):
    folder = make_case(tmp_path)
    result = run_pmpm([folder, "--check", "--set", "mesh.box.cells=[5,5,5]"])
    assert result.returncode == 0, result.stderr
    assert "125 cells" in result.stdout and "2 at start" in result.stdout
    assert not (folder / "output").exists()

    first = run_pmpm([folder, "--quiet"])
    assert first.returncode == 0, first.stderr
    summary = json.loads((folder / "output" / "summary.json").read_text())
    assert summary["ranks"] == 2 and summary["steps"] == 4
    peak = summary["peak_memory_mb"]   # two Python processes with PETSc: tens of MB each at least
    assert 20 < peak["largest_rank"] < peak["all_ranks"] <= 2 * peak["largest_rank"]
    before = (folder / "output" / "particles.csv").read_text()
    second = run_pmpm([folder, "--quiet", "--set", "run.end_time=0.01"])
    assert second.returncode == 0, second.stderr
    assert "kept as" in second.stdout
    assert (folder / "output.1" / "particles.csv").read_text() == before
    rows = np.loadtxt(folder / "output" / "particles.csv", delimiter=",", skiprows=1)
    assert rows[:, 0].max() == pytest.approx(0.01)


FLOW = """
[run]
end_time = 0.04
dt = 0.01
output_every = 0.02
[mesh]
box = { lower = [0, 0, 0], upper = [0.1, 0.1, 0.1], cells = [6, 5, 4] }
[fluid]
density = 1000.0
viscosity = 0.01
pressure_rtol = 1e-12
[boundary.zmax]
velocity = [0.05, 0.0, 0.0]
[[particles.add]]
position = [0.05, 0.05, 0.05]
velocity = [0.1, 0.0, 0.0]
radius = 0.02
density = 2000.0
[[particles.add]]
position = [0.02, 0.02, 0.08]
radius = 0.01
density = 1000.0
[collisions]
"""


def test_one_and_two_ranks_write_the_same_files(tmp_path):
    """fields.h5 (mesh and fluid fields, cell by cell via cell_centers; particles) and particles.csv
    agree on 1 and 2 ranks, for a scene with flow, coupling and collisions."""
    import h5py

    folder = make_case(tmp_path, FLOW)
    outputs = {}
    for ranks in (1, 2):
        result = run_pmpm([folder, "--quiet", "--output", tmp_path / f"out{ranks}"], ranks=ranks)
        assert result.returncode == 0, result.stderr
        outputs[ranks] = tmp_path / f"out{ranks}"
    with h5py.File(outputs[1] / "fields.h5", "r") as one, h5py.File(outputs[2] / "fields.h5", "r") as two:
        centers = one["mesh/cell_centers"][...]
        assert centers.shape == (120, 3)
        np.testing.assert_allclose(two["mesh/cell_centers"][...], centers, rtol=0, atol=1e-15)
        np.testing.assert_allclose(two["mesh/cell_volumes"][...], one["mesh/cell_volumes"][...], rtol=1e-14)
        for f in (one, two):  # connectivity names the same vertex coordinates
            assert np.allclose(f["mesh/vertices"][...][f["mesh/cells"][...]].mean(axis=1), centers, atol=1e-15)
        assert sorted(one["output"]) == sorted(two["output"]) == ["000000", "000001", "000002"]
        for group in one["output"]:
            a, b = one[f"output/{group}"], two[f"output/{group}"]
            assert a.attrs["time"] == b.attrs["time"]
            for name in ("velocity", "pressure", "volume_fraction"):
                scale = max(np.abs(a[name][...]).max(), 1e-30)
                np.testing.assert_allclose(b[name][...], a[name][...], rtol=0, atol=1e-9 * scale, err_msg=name)
            np.testing.assert_allclose(b["particles/position"][...], a["particles/position"][...], rtol=0, atol=1e-12)
        assert np.abs(one["output/000002/velocity"][...]).max() > 1e-3, "the flow moves"
    a = np.loadtxt(outputs[1] / "particles.csv", delimiter=",", skiprows=1)
    b = np.loadtxt(outputs[2] / "particles.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(a[:, :13], b[:, :13], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(a[:, 13:], b[:, 13:], rtol=0, atol=1e-9 * np.abs(a[:, 13:]).max())


def test_xdmf_is_valid_and_points_at_the_data(tmp_path):
    """fields.xdmf parses as XML, and every HDF DataItem names a dataset of the stated dimensions."""
    import xml.etree.ElementTree as ElementTree

    import h5py

    folder = make_case(tmp_path, FLOW)
    result = run_pmpm([folder, "--quiet"], ranks=1)
    assert result.returncode == 0, result.stderr
    root = ElementTree.parse(folder / "output" / "fields.xdmf").getroot()
    assert root.tag == "Xdmf"
    items = root.findall(".//DataItem")
    times = [float(t.get("Value")) for t in root.findall(".//Time")]
    assert times == pytest.approx([0.0, 0.02, 0.04])
    with h5py.File(folder / "output" / "fields.h5", "r") as f:
        names = set()
        for item in items:
            file_name, dataset = item.text.strip().split(":")
            assert file_name == "fields.h5"
            assert tuple(int(d) for d in item.get("Dimensions").split()) == f[dataset].shape
            names.add(dataset.rsplit("/", 1)[-1])
    assert {"cells", "vertices", "velocity", "pressure", "volume_fraction", "position"} <= names


def test_petsc_options_reach_the_solver_and_failure_exits_3(tmp_path):
    """Single-dash options go to PETSc: a pressure KSP capped at 1 iteration cannot converge, and
    the run stops with exit 3 and one line naming the solve, the step and what to change."""
    folder = make_case(tmp_path, FLOW)
    result = run_pmpm([folder, "--quiet", "-pressure_ksp_max_it", "1", "-pressure_ksp_rtol", "1e-14"])
    assert result.returncode == 3, result.stderr
    # the start-up warnings (this coarse scene's particles span 1–2 cells) are not the failure's line
    lines = [line for line in result.stderr.splitlines() if line.strip() and not line.startswith("pmpm: warning:")]
    assert len(lines) == 1 and "pressure solve did not converge at step" in lines[0], result.stderr
    assert "pc_type" in lines[0] and "Traceback" not in result.stderr
    # the last good state (here the initial one) was written before stopping
    import h5py
    with h5py.File(folder / "output" / "fields.h5", "r") as f:
        assert [f[f"output/{g}"].attrs["time"] for g in sorted(f["output"])] == [0.0, 0.0]
        assert np.isfinite(f["output/000001/velocity"][...]).all()
    summary = json.loads((folder / "output" / "summary.json").read_text())
    assert summary["status"] == "numerical failure"


def test_the_command_ends_after_petscs_report(tmp_path):
    """The command ends its process itself once its files are written (``__main__.leave``, without
    the interpreter's teardown): PETSc is finalized first, so a ``-log_view`` report comes out
    whole, to its last line, and the status is the run's."""
    folder = make_case(tmp_path)
    result = run_pmpm([folder, "--quiet", "-log_view"])
    assert result.returncode == 0, result.stderr
    assert result.stdout.count("PETSc Performance Summary") == 1, result.stdout
    assert "#End of PETSc Option Table entries" in result.stdout and "Using libraries:" in result.stdout
    assert json.loads((folder / "output" / "summary.json").read_text())["status"] == "completed"


def test_checkpoint_and_restart_continue_the_run(tmp_path):
    """A run stopped at t = 0.02 and restarted from its checkpoint (on another number of ranks)
    ends where the uninterrupted run ends; a bad checkpoint is refused with exit 2."""
    folder = make_case(tmp_path, FLOW.replace("output_every = 0.02", "output_every = 0.02\ncheckpoint_every = 0.02"))
    whole = run_pmpm([folder, "--quiet", "--output", tmp_path / "whole"], ranks=1)
    assert whole.returncode == 0, whole.stderr
    assert (tmp_path / "whole" / "checkpoint.h5").exists() and not (tmp_path / "whole" / "checkpoint.h5.tmp").exists()
    half = run_pmpm([folder, "--quiet", "--output", tmp_path / "half", "--set", "run.end_time=0.02"], ranks=1)
    assert half.returncode == 0, half.stderr
    rest = run_pmpm([folder, "--quiet", "--output", tmp_path / "rest", "--restart", tmp_path / "half" / "checkpoint.h5"])
    assert rest.returncode == 0, rest.stderr
    assert "restarting from" in rest.stdout
    a = np.loadtxt(tmp_path / "whole" / "particles.csv", delimiter=",", skiprows=1)
    b = np.loadtxt(tmp_path / "rest" / "particles.csv", delimiter=",", skiprows=1)
    last_a, last_b = a[a[:, 0] == a[:, 0].max()], b[b[:, 0] == b[:, 0].max()]
    assert last_a[0, 0] == last_b[0, 0] == pytest.approx(0.04)
    np.testing.assert_allclose(last_b[:, :13], last_a[:, :13], rtol=1e-8, atol=1e-12)
    import h5py
    with h5py.File(tmp_path / "whole" / "fields.h5", "r") as f, h5py.File(tmp_path / "rest" / "fields.h5", "r") as g:
        u_whole, u_rest = f["output/000002/velocity"][...], g["output/000001/velocity"][...]
        np.testing.assert_allclose(u_rest, u_whole, rtol=0, atol=1e-8 * np.abs(u_whole).max())
    (tmp_path / "junk.h5").write_text("not hdf5")
    bad = run_pmpm([folder, "--quiet", "--restart", tmp_path / "junk.h5"])
    assert bad.returncode == 2 and "not a pmpm checkpoint" in bad.stderr and "Traceback" not in bad.stderr


@pytest.mark.parametrize("given, expected", [
    ({}, "^cm"),                                                             # no launcher: one process
    ({"OMPI_COMM_WORLD_SIZE": "4", "OMPI_COMM_WORLD_LOCAL_SIZE": "4"}, "^cm"),   # mpirun, one node
    ({"OMPI_COMM_WORLD_SIZE": "8", "OMPI_COMM_WORLD_LOCAL_SIZE": "4"}, None),    # mpirun, two nodes
    ({"SLURM_PROCID": "0"}, None),                                           # another launcher
    ({"OMPI_MCA_pml": "ucx"}, "ucx"),                                        # the user's choice
])
def test_open_mpis_internode_layer_skipped_on_one_node_only(given, expected):
    """Importing pmpm before MPI starts: Open MPI's ``cm`` layer (probing it costs 0.2 s a
    process here) is skipped where every rank is on this node, and only there."""
    code = "import os, pmpm; print(os.environ.get('OMPI_MCA_pml'))"
    environment = {name: value for name, value in subprocess_env().items()
                   if not name.startswith(("PMIX_", "PMI_", "SLURM_"))}
    result = subprocess.run([PYTHON, "-c", code], env={**environment, **given}, capture_output=True, text=True,
                            check=True)
    assert result.stdout.strip() == str(expected)
