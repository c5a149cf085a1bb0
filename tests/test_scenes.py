"""The paper's scenes (cases/), each in a short version on 2 ranks, asserting what it must show.

Every scene runs as a user runs it, ``mpirun -n 2 python -m pmpm cases/<scene>``, with ``--set``
overrides that make it short (and coarser where it says so); the full versions and their run
times are in the README.
"""
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, mpirun_command, subprocess_env


def run_scene(tmp_path, scene, *settings, ranks=2, timeout=600):
    """Run ``cases/<scene>`` with ``--set`` overrides into tmp_path/scene; (particles.csv table,
    summary.json)."""
    output = tmp_path / scene
    command = mpirun_command(ranks) + ["-m", "pmpm", str(ROOT / "cases" / scene), "--quiet", "--output", str(output)]
    for setting in settings:
        command += ["--set", setting]
    result = subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=subprocess_env())
    assert result.returncode == 0, result.stderr
    table = np.genfromtxt(output / "particles.csv", delimiter=",", names=True)
    return table, json.loads((output / "summary.json").read_text())


def rows_at(table, time):
    return table[np.isclose(table["time"], time)]


def test_ventilated_box(tmp_path):
    """Figure 4, 0.15 s on a mesh twice as coarse: the air that comes in low on one side leaves high
    on the other (outflow = inflow, to the pressure solver's tolerance), and it rolls each of the
    five spheres downstream along the floor, none leaving the box."""
    table, summary = run_scene(tmp_path, "ventilated_box", "run.end_time=0.15", "mesh.box.cells=[30,15,15]")
    flux = summary["diagnostics"]["boundary_volume_flux"]
    assert flux["inlet"] == pytest.approx(-0.06, rel=1e-9)
    assert flux["outlet"] == pytest.approx(0.06, rel=1e-6)
    start, end = rows_at(table, 0.0), rows_at(table, table["time"].max())
    assert summary["particles"] == 5 and len(end) == 5
    assert (end["x"] - start["x"] > 1e-3).all(), "every sphere moves downstream"
    assert np.allclose(end["z"], start["z"], rtol=1e-3), "rolling on the floor"
