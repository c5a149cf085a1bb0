"""Exceptions that map to pmpm's exit statuses (README, "The command line"): CaseError → 2,
NumericalError → 3, Stopped → 128 + the signal."""


class CaseError(Exception):
    """Bad user input: case file, mesh, particle file or command-line option (exit status 2).

    The message is one line that names the file, the key or line, what is wrong and what is
    allowed, e.g. ``case.toml: [fluid] viscosity = -0.001: must be > 0 (Pa s)``.
    """

    exit_status = 2


class NumericalError(Exception):
    """A numerical failure: instability, NaN, a solver that did not converge (exit status 3).

    The message says at which step and time, which particle or cell, and what to change.
    """

    exit_status = 3


class Stopped(Exception):
    """The run was asked to stop by a signal (SIGTERM from a batch scheduler, SIGINT from Ctrl-C)
    and stopped cleanly after a whole step, its state written (exit status 128 + the signal's
    number, as a shell reports a process ended by that signal: 143 for SIGTERM, 130 for SIGINT).
    """

    def __init__(self, message: str, signal_number: int):
        super().__init__(message)
        self.exit_status = 128 + signal_number


def one_line(text: str) -> str:
    """``text`` with its control characters (newlines, carriage returns, ...) escaped: a message that
    quotes user input (``--set "a=\\n"``) stays the one line the README promises."""
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)
