"""Where particles come from: the initial set (particle file, [[particles.add]]) and the
continuous injections of the paper's Table 1 (point, random, cylindrical; moving locations).

Every decision is a function of the case and the seed only, so every rank takes the same one:
random positions come from ``numpy.random.default_rng((seed, injection, release))``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import CaseError

MOTION_CODES = {"free": 0, "fixed": 1, "prescribed": 2}
FILE_COLUMNS = ("x", "y", "z", "vx", "vy", "vz", "wx", "wy", "wz", "radius", "density")
REQUIRED_COLUMNS = ("x", "y", "z", "radius", "density")


@dataclass
class NewParticles:
    """Particles to add, as arrays (SI): x, v, omega (n,3); radius, density (n,); motion (n,) int8."""

    x: np.ndarray
    v: np.ndarray
    omega: np.ndarray
    radius: np.ndarray
    density: np.ndarray
    motion: np.ndarray

    @classmethod
    def empty(cls) -> "NewParticles":
        z3, z1 = np.zeros((0, 3)), np.zeros(0)
        return cls(z3, z3.copy(), z3.copy(), z1, z1.copy(), np.zeros(0, np.int8))

    @classmethod
    def concatenate(cls, parts: list["NewParticles"]) -> "NewParticles":
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                     ("x", "v", "omega", "radius", "density", "motion")))

    def __len__(self):
        return len(self.radius)


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


def rotation_matrix(angle_vector: np.ndarray) -> np.ndarray:
    """Rotation by |angle_vector| radians about its direction (Rodrigues)."""
    angle = float(np.linalg.norm(angle_vector))
    if angle == 0.0:
        return np.eye(3)
    k = np.asarray(angle_vector) / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


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
        s, n = self.section, self.section.count
        t = self.release_time(k)
        if s.kind == "random":
            rng = np.random.default_rng((self.seed, self.index, k))
            lower, upper = np.array(s.lower), np.array(s.upper)
            x = lower + rng.random((n, 3)) * (upper - lower)
            v = np.tile(s.velocity, (n, 1))
        elif s.kind == "cylindrical":
            axis = np.array(s.axis) / np.linalg.norm(s.axis)
            e1 = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(axis, e1)
            radial = np.cos(s.theta) * e1 + np.sin(s.theta) * e2
            tangential = -np.sin(s.theta) * e1 + np.cos(s.theta) * e2
            x = np.tile(np.array(s.origin) + s.r * radial + s.z * axis, (n, 1))
            # velocity = (v_r, v_theta, v_z) in the injection's cylindrical frame
            v = np.tile(s.velocity[0] * radial + s.velocity[1] * tangential + s.velocity[2] * axis, (n, 1))
        else:
            x = np.tile(s.position, (n, 1))
            v = np.tile(s.velocity, (n, 1))
        # a moving / rotating injection location (Table 1): the release point follows a rigid motion
        center = np.array(s.rotation_center)
        x = center + (x - center) @ rotation_matrix(np.array(s.location_angular_velocity) * t).T \
            + np.array(s.location_velocity) * t
        return NewParticles(x, v, np.tile(s.angular_velocity, (n, 1)), np.full(n, s.radius),
                            np.full(n, s.density), np.zeros(n, np.int8))


def build_injectors(case) -> tuple[Injector, ...]:
    return tuple(Injector(section, i, case.run.seed) for i, section in enumerate(case.injections))
