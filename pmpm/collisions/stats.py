"""The counters a step reports (``ContactStep.stats``): names, and their slots in the int64 array
the compiled kernels count into."""
from __future__ import annotations

import numpy as np

# slots of the int64 counters (the compiled kernels count into them; the solver into the last)
PAIR, WALL, RESTING, EVENTS, CAPPED, DEPOSITED, SWEEPS, SETTLES, CLAMPS, EXCEEDED = range(10)
NAMES = ("particle_collisions",  # impacts between particles (faster than the rest speed in a dense step)
         "wall_collisions",      # impacts with walls
         "resting_contacts",     # contacts in resting solves (dense step: active ones that are not impacts)
         "events",               # impacts taken in time order
         "capped",               # 1 if the event budget ran out (the rest of the step inelastic)
         "deposited",            # particles deposited
         "sweeps",               # Gauss–Seidel sweeps, all solves of the step
         "settles",              # resting solves (the step's start and slow impacts)
         "energy_clamps",        # solves whose result would have raised the kinetic energy (limited)
         "searches_exceeded")    # speeds that outgrew the broad search (the step was searched again)
# counted in Python
EXTRA = ("dense_steps", "dense_contacts", "contacts", "overlaps_removed")


def new_counters() -> np.ndarray:
    return np.zeros(len(NAMES), np.int64)


def as_dict(counters: np.ndarray, extra: dict) -> dict:
    """The counters by name (ints; ``capped`` a bool), with the Python-side ones."""
    stats = {name: int(value) for name, value in zip(NAMES, counters)}
    stats["capped"] = bool(stats["capped"])
    stats.update({name: int(extra.get(name, 0)) for name in EXTRA})
    return stats
