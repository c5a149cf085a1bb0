"""Loading the compiled kernels: numba is imported on their first use, so a run without
[collisions] never loads it (~0.3 s).

numba caches each compiled function on disk next to its source (``__pycache__``) and checks only
the timestamp of that function's own file, not of the files whose functions it calls. The kernels
call each other across files, so the loader keeps a digest of the compiled modules' sources (and
of the constants they read) with the cache and clears the package's cached kernels when any of
them changed. Ranks that compile
at once do not clash: numba writes its cache files under a temporary name and renames them.
With ``NUMBA_CACHE_DIR`` set, numba caches elsewhere and that directory is the user's to clear.
"""
from __future__ import annotations

import hashlib
import os
from functools import cache
from pathlib import Path
from types import SimpleNamespace

HERE = Path(__file__).resolve().parent
COMPILED = ("block", "cell_list", "contact_times", "deposition", "event_queue", "events", "impulses",
            "messages", "narrow", "settings", "stats", "step_arrays", "wall_grid")  # and what they import


def sources_digest() -> str:
    """A digest of the compiled modules' sources: the cache was made from them while it is unchanged."""
    return hashlib.sha1(b"".join((HERE / f"{name}.py").read_bytes() for name in COMPILED)).hexdigest()


def cache_is_current(folder: Path = HERE / "__pycache__") -> bool:
    """Whether the kernels' cache in ``folder`` was made from these sources (its stamp), so that a
    run loads them instead of compiling them; true where pmpm cannot tell (``NUMBA_CACHE_DIR``
    set, or a package it cannot write, whose kernels numba caches elsewhere). Reads only."""
    if os.environ.get("NUMBA_CACHE_DIR") or not os.access(folder if folder.exists() else folder.parent, os.W_OK):
        return True
    try:
        return (folder / "kernels.sha1").read_text() == sources_digest()
    except OSError:
        return False


def clear_stale_cache() -> None:
    """Remove this package's numba cache files if any of its sources changed since they were made
    (``cache_is_current``), and stamp the cache with the sources' digest."""
    folder = HERE / "__pycache__"
    if cache_is_current(folder):
        return
    try:
        folder.mkdir(exist_ok=True)
        for path in chain_globs(folder, ("*.nbi", "*.nbc")):
            path.unlink(missing_ok=True)
        temporary = folder / f"kernels.sha1.{os.getpid()}"
        temporary.write_text(sources_digest())
        os.replace(temporary, folder / "kernels.sha1")
    except OSError:  # a read-only installation: numba falls back on its own cache folder
        pass


def chain_globs(folder: Path, patterns) -> list[Path]:
    return [path for pattern in patterns for path in folder.glob(pattern)]


@cache
def kernels() -> SimpleNamespace:
    """The compiled modules (imported, and so compiled or loaded from the cache, on first call)."""
    clear_stale_cache()
    from . import block, cell_list, contact_times, deposition, events, impulses, narrow, step_arrays, wall_grid
    return SimpleNamespace(block=block, cell_list=cell_list, contact_times=contact_times, deposition=deposition,
                           events=events, impulses=impulses, narrow=narrow, step_arrays=step_arrays, wall_grid=wall_grid)
