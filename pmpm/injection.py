"""Where particles come from: the initial set (particle file, [[particles.add]]) and the
continuous injections of the paper's Table 1 (point, random, cylindrical; moving locations).

Every decision is a function of the case and the seed only, so every rank takes the same one:
random positions come from ``numpy.random.default_rng((seed, injection, release))``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .arrays import rotation_matrix
from .errors import CaseError

MOTION_CODES = {"free": 0, "fixed": 1, "prescribed": 2}
FILE_COLUMNS = ("x", "y", "z", "vx", "vy", "vz", "wx", "wy", "wz", "radius", "density")
REQUIRED_COLUMNS = ("x", "y", "z", "radius", "density")


@dataclass
class NewParticles:
    """Particles to add, as arrays (SI): x, v, omega (n,3); radius, density (n,); motion (n,) int8;
    ``time`` (n,) when they are released (s; injections); ``alternatives`` (a, n, 3) other
    positions to try, in order, where the first cannot take the particle (random injections;
    NaN where there is none)."""

    x: np.ndarray
    v: np.ndarray
    omega: np.ndarray
    radius: np.ndarray
    density: np.ndarray
    motion: np.ndarray
    time: np.ndarray | None = None
    alternatives: np.ndarray | None = None

    @classmethod
    def empty(cls) -> "NewParticles":
        z3, z1 = np.zeros((0, 3)), np.zeros(0)
        return cls(z3, z3.copy(), z3.copy(), z1, z1.copy(), np.zeros(0, np.int8))

    @classmethod
    def concatenate(cls, parts: list["NewParticles"]) -> "NewParticles":
        if not parts:
            return cls.empty()
        arrays = [np.concatenate([getattr(p, f) for p in parts]) for f in
                  ("x", "v", "omega", "radius", "density", "motion")]
        times = np.concatenate([p.release_times for p in parts])
        alternatives = np.concatenate([p.other_positions for p in parts], axis=1)
        return cls(*arrays, times, alternatives)

    @property
    def release_times(self) -> np.ndarray:
        return np.zeros(len(self)) if self.time is None else self.time

    @property
    def other_positions(self) -> np.ndarray:
        """(RELEASE_ATTEMPTS − 1, n, 3): the alternatives, NaN where there are none."""
        if self.alternatives is not None:
            return self.alternatives
        return np.full((RELEASE_ATTEMPTS - 1, len(self), 3), np.nan)

    def __len__(self):
        return len(self.radius)


RELEASE_ATTEMPTS = 20   # positions a random injection tries for each particle before it drops it


COLUMN_UNITS = {"x": "m", "y": "m", "z": "m", "vx": "m/s", "vy": "m/s", "vz": "m/s",
                "wx": "rad/s", "wy": "rad/s", "wz": "rad/s", "radius": "m", "density": "kg/m³"}


def read_particle_file(path: Path) -> NewParticles:
    """The ASCII particle file: a header naming the columns, one particle a line (commas or blanks)."""
    if path.is_dir():
        raise CaseError(f"{path}: is a folder, not a particle file")
    if not path.is_file():
        raise CaseError(f"{path}: particle file not found")
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark is not part of the header
    except (OSError, UnicodeDecodeError) as error:
        raise CaseError(f"{path}: cannot read the particle file: {getattr(error, 'strerror', None) or error}") from None
    # (line number in the file, text) of the lines that hold something
    lines = [(number, line) for number, line in enumerate(text.splitlines(), start=1)
             if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise CaseError(f"{path}: empty particle file (expected a header line naming the columns)")
    header_number, header_line = lines[0]
    header = header_line.replace(",", " ").split()
    for name in header:
        if name not in FILE_COLUMNS:
            raise CaseError(f"{path}: line {header_number}: unknown column \"{name}\"; allowed: {' '.join(FILE_COLUMNS)}")
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise CaseError(f"{path}: line {header_number}: missing column(s) {', '.join(missing)}")
    rows = []
    for number, line in lines[1:]:
        fields = line.replace(",", " ").split()
        try:
            values = [float(v) for v in fields]
        except ValueError:
            raise CaseError(f"{path}: line {number}: not a number in \"{line.strip()}\"") from None
        if len(values) != len(header):
            raise CaseError(f"{path}: line {number}: {len(values)} values for {len(header)} columns")
        rows.append(values)
    table = np.array(rows, float).reshape(-1, len(header))
    # the first bad value, named by its line and column
    positive = np.array([name in ("radius", "density") for name in header])
    bad = ~np.isfinite(table) | (positive & ~(table > 0))
    if bad.any():
        row, col = np.argwhere(bad)[0]
        name = header[col]
        rule = "finite and > 0" if positive[col] else "finite"
        raise CaseError(f"{path}: line {lines[1 + row][0]}: {name} = {table[row, col]:g}: must be {rule} "
                        f"({COLUMN_UNITS[name]})")
    column = {name: table[:, i] for i, name in enumerate(header)}
    zeros = np.zeros(len(table))

    def vec(names):
        return np.column_stack([column.get(n, zeros) for n in names])

    return NewParticles(vec("xyz"), vec(("vx", "vy", "vz")), vec(("wx", "wy", "wz")),
                        column["radius"].copy(), column["density"].copy(), np.zeros(len(table), np.int8))


def initial_particles(case) -> NewParticles:
    """The particles present at t = 0: the particle file first, then [[particles.add]] in order."""
    if case.particles is None:
        return NewParticles.empty()
    parts = []
    if case.particles.file:
        parts.append(read_particle_file(case.resolve(case.particles.file)))
    for p in case.particles_add:
        parts.append(NewParticles(np.array([p.position]), np.array([p.velocity]), np.array([p.angular_velocity]),
                                  np.array([p.radius]), np.array([p.density]),
                                  np.array([MOTION_CODES[p.motion]], np.int8)))
    return NewParticles.concatenate(parts)


def cylinder_frame(axis) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors (reference, axis × reference, axis) of a cylindrical injection: θ is measured
    from the reference direction, the global axis that follows the axis's largest component in the
    cyclic order x → y → z → x, made perpendicular to the axis (axis z: θ from +x towards +y; axis
    x: from +y towards +z; axis y: from +z towards +x)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    reference = np.eye(3)[(int(np.argmax(np.abs(axis))) + 1) % 3]
    reference = reference - (reference @ axis) * axis
    reference /= np.linalg.norm(reference)
    return reference, np.cross(axis, reference), axis


class Injector:
    """One [[injection]] table: releases ``count`` particles at start, start + interval, ... <= stop.
    Holds the table only; which release is next is part of the run state."""

    def __init__(self, section, index: int, seed: int):
        self.section, self.index, self.seed = section, index, seed

    def release_time(self, k: int) -> float:
        return self.section.start + k * self.section.interval

    def due(self, next_release: int, time_end: float) -> tuple[NewParticles, int]:
        """The particles of every release from ``next_release`` on with time <= time_end, and the
        index of the release after them."""
        parts = []
        s = self.section
        while self.release_time(next_release) <= min(time_end, s.stop) + 1e-12 * max(1.0, abs(time_end)):
            parts.append(self.release(next_release))
            next_release += 1
        return NewParticles.concatenate(parts), next_release

    def release(self, k: int) -> NewParticles:
        """Release ``k``: its particles where and as the injection sets them free. A moving or
        rotating location (Table 1) carries the release point, the velocity and the spin with it,
        and adds its own motion there: a particle leaving a rotating fan blade leaves at the
        blade's speed."""
        s, n = self.section, self.section.count
        t = self.release_time(k)
        alternatives = None
        if s.kind == "random":
            lower, upper = np.array(s.lower), np.array(s.upper)
            draws = np.stack([np.random.default_rng((self.seed, self.index, k) + ((attempt,) if attempt else ()))
                              .random((n, 3)) for attempt in range(RELEASE_ATTEMPTS)])
            points = lower + draws * (upper - lower)          # (attempts, n, 3); the first as before retries
            x, alternatives = points[0], points[1:]
            v = np.tile(s.velocity, (n, 1))
        elif s.kind == "cylindrical":
            reference, normal, axis = cylinder_frame(s.axis)
            radial = np.cos(s.theta) * reference + np.sin(s.theta) * normal
            tangential = -np.sin(s.theta) * reference + np.cos(s.theta) * normal
            x = np.tile(np.array(s.origin) + s.r * radial + s.z * axis, (n, 1))
            # velocity = (v_r, v_theta, v_z) in the injection's cylindrical frame
            v = np.tile(s.velocity[0] * radial + s.velocity[1] * tangential + s.velocity[2] * axis, (n, 1))
        else:
            x = np.tile(s.position, (n, 1))
            v = np.tile(s.velocity, (n, 1))
        centre, spin = np.array(s.rotation_center), np.array(s.location_angular_velocity)
        shift, turn = np.array(s.location_velocity) * t, rotation_matrix(spin * t)

        def carried(points):      # the point of the moving location that was at ``points`` at t = 0
            return centre + (points - centre) @ turn.T + shift

        arm = (x - centre) @ turn.T
        x = carried(x)
        v = v @ turn.T + np.array(s.location_velocity) + np.cross(spin, arm)
        omega = np.tile(turn @ np.array(s.angular_velocity) + spin, (n, 1))
        if alternatives is not None:
            alternatives = carried(alternatives)
        return NewParticles(x, v, omega, np.full(n, s.radius), np.full(n, s.density), np.zeros(n, np.int8),
                            np.full(n, t), alternatives)


def build_injectors(case) -> tuple[Injector, ...]:
    return tuple(Injector(section, i, case.run.seed) for i, section in enumerate(case.injections))
