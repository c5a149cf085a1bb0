"""The folder a benchmark's runs write their outputs into: in the system's temporary folder, removed
at the end unless the command's ``--keep`` keeps it (then its path is printed)."""
from __future__ import annotations

import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path


def add_keep_option(parser) -> None:
    """The ``--keep`` flag of an ``argparse`` parser."""
    parser.add_argument("--keep", action="store_true",
                        help="keep the runs' folder (its path printed at the end) instead of removing it")


@contextmanager
def runs_folder(prefix: str, keep: bool):
    """A new folder named ``prefix``…; removed on leaving (whatever happened inside), or kept and its
    path printed with ``keep``."""
    folder = Path(tempfile.mkdtemp(prefix=prefix))
    try:
        yield folder
    finally:
        if keep:
            print(f"(runs in {folder})")
        else:
            shutil.rmtree(folder, ignore_errors=True)
