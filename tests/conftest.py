"""Shared test fixtures. Under mpirun, a failing test aborts every rank so none hangs."""
import os
import sys
from pathlib import Path

import pytest

os.environ.setdefault("H5PY_ALWAYS_USE_MPI", "1")  # Debian's h5py: the MPI build even without mpirun

ROOT = Path(__file__).resolve().parents[1]
PYTHON = str(ROOT / ".venv" / "bin" / "python") if (ROOT / ".venv" / "bin" / "python").exists() else sys.executable


def mpirun_command(n: int) -> list[str]:
    """``mpirun -n N python`` with the flags this machine needs (root, 2 cores)."""
    flags = ["--oversubscribe", "--quiet"] + (["--allow-run-as-root"] if os.geteuid() == 0 else [])
    return ["mpirun", *flags, "-n", str(n), PYTHON]


def subprocess_env() -> dict:
    """The environment for a child mpirun: without the MPI variables of this (possibly MPI-initialised)
    pytest process, which would make the child's mpirun believe it runs inside this job."""
    return {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_", "OPAL_", "ORTE_"))}


def pytest_runtest_logreport(report):
    if report.failed and report.when == "call":
        from mpi4py import MPI
        if MPI.COMM_WORLD.size > 1:
            sys.stderr.write(f"\n[rank {MPI.COMM_WORLD.rank}] {report.nodeid} failed:\n{report.longreprtext}\n")
            sys.stderr.flush()
            MPI.COMM_WORLD.Abort(1)


@pytest.fixture
def comm():
    from mpi4py import MPI
    return MPI.COMM_WORLD


@pytest.fixture
def shared_tmp(tmp_path, comm):
    """A temporary folder that every rank sees (rank 0's tmp_path)."""
    return Path(comm.bcast(str(tmp_path), root=0))
