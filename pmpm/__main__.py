"""Command line (README, "The command line"): ``python -m pmpm CASE [--output DIR] [--set K=V]... [--check] [--quiet]``.

Single-dash options go to PETSc's options database (``-pressure_ksp_type cg``). Exit status:
0 done, 2 bad input (CaseError), 3 numerical failure (NumericalError), 128 + the signal's number when
stopped by SIGTERM or SIGINT after writing its state (Stopped: 143, 130), 1 anything else.
"""
from __future__ import annotations

import argparse
import ctypes
import os
import sys

USAGE = """pmpm CASE [--output DIR] [--set KEY=VALUE ...] [--check] [--restart FILE] [--quiet] [-petsc_option value ...]

CASE is a folder holding case.toml, or a .toml file. Examples:
  pmpm cases/settling_sphere
  mpirun -n 2 python -m pmpm cases/cavity --set fluid.viscosity=0.01 -pressure_ksp_monitor"""


def split_petsc_options(argv: list[str]) -> tuple[list[str], list[str]]:
    """Separate PETSc's single-dash options (with their values) from pmpm's own arguments."""
    ours, petsc = [], []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg.startswith("-") and not arg.startswith("--") and len(arg) > 2 and not _is_number(arg):
            petsc.append(arg)
            if i + 1 < len(argv) and (not argv[i + 1].startswith("-") or _is_number(argv[i + 1])):
                petsc.append(argv[i + 1])
                i += 1
        else:
            ours.append(arg)
        i += 1
    return ours, petsc


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


class _Parser(argparse.ArgumentParser):
    """argparse that raises instead of printing usage and exiting (so every rank exits the same way)."""

    def error(self, message):
        from .errors import CaseError
        raise CaseError(f"command line: {message} (see pmpm --help)")


def parse_arguments(argv):
    parser = _Parser(prog="pmpm", usage=USAGE, add_help=True)
    parser.add_argument("case", help="case folder or .toml file")
    parser.add_argument("--output", help="output folder (default: output/ beside the case file)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a case value by its dotted TOML path")
    parser.add_argument("--check", action="store_true", help="validate and describe the run, then exit")
    parser.add_argument("--restart", metavar="FILE", help="continue from a checkpoint")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "render":  # pictures of a run's output: one process, no MPI or PETSc
        from .render import main as render_main
        return render_main(argv[1:])
    ours, petsc_options = split_petsc_options(argv)
    import petsc4py
    petsc4py.init([sys.argv[0]] + petsc_options)
    from mpi4py import MPI

    from .errors import CaseError, NumericalError, Stopped, one_line

    comm = MPI.COMM_WORLD
    try:
        arguments = parse_arguments(ours)
        from .simulation import run_from_arguments
        run_from_arguments(comm, arguments)
        return 0
    except SystemExit as exit_request:  # --help
        return int(exit_request.code or 0)
    except (CaseError, NumericalError, Stopped) as error:
        if comm.rank == 0:
            kind = {CaseError: "error: ", NumericalError: "numerical failure: ", Stopped: ""}[type(error)]
            print(f"pmpm: {kind}{one_line(str(error))}", file=sys.stderr, flush=True)
        # Errors are collective (pmpm.parallel.agree). Only rank 0 reports the status, after the
        # others wait for its line: mpirun may drop a rank's output once another exits non-zero.
        comm.Barrier()
        return error.exit_status if comm.rank == 0 else 0
    except KeyboardInterrupt:
        return 130
    except BaseException:
        # A bug, not a user mistake: show it, and take every rank down rather than leave one waiting.
        import traceback
        traceback.print_exc()
        sys.stderr.flush()
        if comm.size > 1:
            comm.Abort(1)
        return 1


def leave(status: int) -> None:
    """End the command with ``status``. Every output file is closed by now; PETSc is finalized (its
    -log_view report printed, and MPI finalized with it) and the streams flushed, then the process
    ends at once: the interpreter's own teardown of the compiled kernels would take another 0.2 s
    of every run (docs/collisions_log.md, "Fourteenth session")."""
    if "petsc4py.PETSc" not in sys.modules:   # (render: no PETSc, nothing compiled)
        sys.exit(status)
    from mpi4py import MPI
    from petsc4py import PETSc
    sys.stdout.flush()
    sys.stderr.flush()
    PETSc._finalize()   # (what petsc4py does at exit; MPI too, where PETSc started it)
    if not MPI.Is_finalized():
        MPI.Finalize()
    ctypes.CDLL(None).fflush(None)   # the C library's buffers too (PETSc prints through them)
    os._exit(status)


if __name__ == "__main__":
    leave(main())
