"""The contact record of a step and the contact memory kept between steps (dataclasses of arrays).

``ContactRecord``: every contact that may act within one step (the broad search's candidates that
the narrow phase kept), as arrays over contacts sorted by first particle, then the other body
(walls last), then the triangle: the order of every sweep, independent of the search.

``ContactMemory``: what the solver remembers from one step to the next, the impulses of the
contacts that pushed, keyed by particle ids (and wall triangle), so it survives particles being
added or removed and can be written to a checkpoint (``to_arrays``/``from_arrays``).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from . import jit

ID_LIMIT = 1 << 31        # particle ids below this, triangles below 2^30, fit the int64 keys


@dataclass
class ContactRecord:
    """Contacts of one step (m of them; SI).

    first, second : (m,) int64 rows of the bodies; the normal points towards ``first``; for a
        wall ``second`` is n (the world body: zero velocity, infinite mass). first < second.
    triangle : (m,) int64 wall triangle, −1 between particles.
    normal : (m, 3) unit normal at the step's start; gap : (m,) m (negative: overlapping).
    face : (m,) bool, a wall contact inside the triangle's face (pairs: True).
    time : (m,) s, first contact time within the step at the start velocities (eq. 5-7), inf if none.
    wall_velocity : (m, 3) m/s, the wall surface velocity at the contact point (0 between particles).
    restitution, friction, rolling_friction : (m,) the contact's coefficients.
    """

    first: np.ndarray
    second: np.ndarray
    triangle: np.ndarray
    normal: np.ndarray
    gap: np.ndarray
    face: np.ndarray
    time: np.ndarray
    wall_velocity: np.ndarray
    restitution: np.ndarray
    friction: np.ndarray
    rolling_friction: np.ndarray

    def __len__(self) -> int:
        return len(self.first)

    def take(self, rows: np.ndarray) -> "ContactRecord":
        return ContactRecord(*(getattr(self, f.name)[rows] for f in fields(self)))

    def adjacency(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Each particle's contacts as CSR: (start (n + 2,), contact indices), by particle then
        contact (a wall contact is listed under its particle only)."""
        pair = self.triangle < 0
        ends = np.concatenate([self.first, self.second[pair]])
        ids = np.concatenate([np.arange(len(self)), np.flatnonzero(pair)])
        order = np.lexsort((ids, ends))
        start = np.zeros(n + 2, np.int64)
        np.cumsum(np.bincount(ends, minlength=n + 1), out=start[1:])
        return start, ids[order].astype(np.int64)


@dataclass
class ContactMemory:
    """Impulses of the last step's contacts, by particle ids (SI): every contact a dense step
    solved, the contacts that pushed in an event step.

    first_id : (k,) int64, the contact's particle with the smaller id (the normal points to it).
    second_id : (k,) int64, the other particle's id, or −1 − triangle for a wall.
    normal_impulse : (k,) N s; tangential_impulse : (k, 3) N s, the impulse on ``first_id``.
    Rows are sorted by (first_id, second_id).
    """

    first_id: np.ndarray
    second_id: np.ndarray
    normal_impulse: np.ndarray
    tangential_impulse: np.ndarray

    def __len__(self) -> int:
        return len(self.first_id)

    @classmethod
    def empty(cls) -> "ContactMemory":
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)))

    def take(self, rows: np.ndarray) -> "ContactMemory":
        """The contacts ``rows`` (indices or a bool mask; in order, the memory stays sorted)."""
        return ContactMemory(*(getattr(self, f.name)[rows] for f in fields(self)))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The memory as named arrays (for a checkpoint)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_arrays(cls, arrays: dict) -> "ContactMemory":
        """The memory from ``to_arrays``' output (e.g. read back from a checkpoint); also from the
        arrays of the engine before (``keys``, ``normal``, ``tangential``, ``sign``: key
        first · 2^31 + other + 2^30, the tangential impulse on the contact's i, sign −1 where i
        was the key's second particle)."""
        if "keys" in arrays:
            keys = np.asarray(arrays["keys"], np.int64).reshape(-1)
            sign = np.asarray(arrays["sign"], float).reshape(-1)
            return cls(keys // (1 << 31), keys % (1 << 31) - (1 << 30), np.asarray(arrays["normal"], float).reshape(-1),
                       np.asarray(arrays["tangential"], float).reshape(-1, 3) * sign[:, None])
        return cls(np.asarray(arrays["first_id"], np.int64).reshape(-1),
                   np.asarray(arrays["second_id"], np.int64).reshape(-1),
                   np.asarray(arrays["normal_impulse"], float).reshape(-1),
                   np.asarray(arrays["tangential_impulse"], float).reshape(-1, 3))

    def packed(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), 6) float64 rows of the contacts ``rows`` (indices): first and second id, the
        normal impulse, the tangential impulse (ids exact below 2^53): what moves between ranks."""
        return np.column_stack([self.first_id[rows], self.second_id[rows], self.normal_impulse[rows],
                                self.tangential_impulse[rows]]).astype(float)

    @classmethod
    def of_packed(cls, block: np.ndarray) -> "ContactMemory":
        """The contacts of ``block`` (rows as from ``packed``, any order), sorted by (first_id, second_id)."""
        first_id, second_id = block[:, 0].astype(np.int64), block[:, 1].astype(np.int64)
        order = np.argsort(cls.key_of(first_id, second_id), kind="stable")
        return cls(first_id[order], second_id[order], block[order, 2], block[order, 3:6])

    @property
    def keys(self) -> np.ndarray:
        """(k,) int64, one key per contact remembered, ascending (``key_of``)."""
        return self.key_of(self.first_id, self.second_id)

    @staticmethod
    def key_of(first_id: np.ndarray, second_id: np.ndarray) -> np.ndarray:
        """One int64 per contact, ordered as (first_id, second_id)."""
        if len(first_id) and (first_id.max() >= ID_LIMIT or second_id.max() >= ID_LIMIT):
            raise ValueError("particle ids must be below 2^31 for the contact memory")
        return first_id.astype(np.int64) * (1 << 32) + (second_id.astype(np.int64) + ID_LIMIT)

    def recall(self, record: ContactRecord, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The remembered impulses of the record's contacts: (m,) and (m, 3), zero where none
        (compiled: ``step_arrays.recalled``)."""
        return jit.kernels().step_arrays.recalled(record.first, record.second, record.triangle, ids, self.first_id,
                                                  self.second_id, self.normal_impulse, self.tangential_impulse)

    @classmethod
    def remember(cls, record: ContactRecord, ids: np.ndarray, normal_impulse: np.ndarray,
                 tangential_impulse: np.ndarray, keep: np.ndarray | None = None) -> "ContactMemory":
        """The impulses of the record's contacts ``keep`` (default: those that pushed, λ_n > 0)
        (compiled: ``step_arrays.remembered``)."""
        keep = normal_impulse > 0 if keep is None else keep
        *arrays, largest, in_order = jit.kernels().step_arrays.remembered(
            record.first, record.second, record.triangle, ids, keep, normal_impulse, tangential_impulse)
        if largest >= ID_LIMIT:
            raise ValueError("particle ids must be below 2^31 for the contact memory")
        if not in_order:   # rows not sorted by id (a gathered cluster): a stable sort by key
            order = np.argsort(cls.key_of(arrays[0], arrays[1]), kind="stable")
            arrays = [values[order] for values in arrays]
        return cls(*arrays)
