"""What the coupling carries from one step to the next (part of the run state, written whole to
checkpoint.h5 so that a restart continues the same trajectory)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CouplingMemory:
    """The coupling's memory between steps.

    known_id : particles with larger ids have not been in the flow yet (the patch forcing brings
        the fluid they cover up to their motion first)
    under_id, under_momentum, under_centre : the penalty forcing's fluid momentum under each particle
        at the end of the last step (m,) int64 sorted, (m, 6) (kg m/s and its moment about the
        centre), (m, 3) that centre (m); the start of the next step's change, by id
    ringing_id, last_change, ringing : the explicit update's watchdog, by id (m,) sorted: the last
        step's velocity change (m, 3) m/s and how many steps in a row it flipped sign and grew (m,)
    correction_rate : the drag correction's extra rate κ_x (1/s) of each pool of particles
        (n_pools,), for the next step
    correction_relief : its relief β of each pool (n_pools,), for the next step: the share of the
        correlation's force taken off particles whose resolved drag exceeds it
    under_target : the correlation's force on each particle (m, 3) N at the end of the last step,
        by id as ``under_id``
    """

    known_id: int = -1
    under_id: np.ndarray | None = None
    under_momentum: np.ndarray | None = None
    under_centre: np.ndarray | None = None
    ringing_id: np.ndarray | None = None
    last_change: np.ndarray | None = None
    ringing: np.ndarray | None = None
    correction_rate: np.ndarray | None = None
    correction_relief: np.ndarray | None = None
    under_target: np.ndarray | None = None

    def to_arrays(self) -> dict:
        """The arrays to store (absent parts left out)."""
        arrays = {"known_id": np.array(self.known_id, np.int64)}
        for name in ("under_id", "under_momentum", "under_centre", "ringing_id", "last_change", "ringing",
                     "correction_rate", "correction_relief", "under_target"):
            if getattr(self, name) is not None:
                arrays[name] = getattr(self, name)
        return arrays

    @classmethod
    def from_arrays(cls, arrays: dict) -> "CouplingMemory":
        def get(name, dtype, columns=None):
            if name not in arrays:
                return None
            values = np.asarray(arrays[name], dtype)
            return values if columns is None else values.reshape(-1, columns)
        return cls(int(arrays["known_id"]), get("under_id", np.int64), get("under_momentum", float, 6),
                   get("under_centre", float, 3), get("ringing_id", np.int64), get("last_change", float, 3),
                   get("ringing", np.int64),
                   get("correction_rate", float), get("correction_relief", float), get("under_target", float, 3))

    def gathered(self, comm) -> "CouplingMemory":
        """Collective. Where ranks own particles each remembers those it held: every rank's, each
        particle once (its holders remember the same), in id order (for a checkpoint)."""
        parts = comm.allgather(self.to_arrays())
        arrays = dict(parts[0])
        for ids, names in (("under_id", ("under_momentum", "under_centre", "under_target")),
                           ("ringing_id", ("last_change", "ringing"))):
            if ids not in arrays:
                continue
            joined = {name: np.concatenate([part[name] for part in parts])
                      for name in (ids, *names) if name in arrays}
            _, first = np.unique(joined[ids], return_index=True)
            arrays.update({name: values[first] for name, values in joined.items()})
        return CouplingMemory.from_arrays(arrays)


def by_id(known_ids: np.ndarray | None, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each of ``ids`` is in the sorted ``known_ids``: (positions (n,), found (n,) bool)."""
    if known_ids is None or len(known_ids) == 0:
        return np.zeros(len(ids), np.int64), np.zeros(len(ids), bool)
    position = np.minimum(np.searchsorted(known_ids, ids), len(known_ids) - 1)
    return position, known_ids[position] == ids
