"""The fluid in the cells an immersed body covers, driven to the body's prescribed motion.

The same implicit penalty as the particles' (``penalty.cell_rate``: friction and blockage, solved
with the diffusion), towards the body's rigid velocity U = V + Ω × r at the cell centres, with the
body's volume fraction α in each cell (``pmpm.bodies.Body.covered_cells``) where it is at the
step's end. Its motion is prescribed, so the passes have no guess to update: the terms are the
same in each. The force on each body is what the penalty took from the fluid over the step,
F = Σ ρ V κ (u − U) at the projected velocity, with its torque about the rotation centre.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mpi4py import MPI

from ..arrays import sum_rows
from .locate import reference_samples
from .penalty import cell_rate


@dataclass(frozen=True)
class BodyPasses:
    """One step of the bodies' forcing: the covered owned cells (m,), their body (m,), its volume
    fraction there (m,), its share κ of each cell's rate (m,), and the rigid velocity U there (m, 3)."""

    cell: np.ndarray
    body: np.ndarray
    alpha: np.ndarray
    kappa: np.ndarray
    rigid: np.ndarray


class BodyForcing:
    """Forcing of the fluid by the case's bodies on one mesh. Holds settings only.

    Parameters
    ----------
    mesh : pmpm.mesh.Mesh
    bodies : tuple of pmpm.bodies.Body
    section : the case's [coupling] section (subcell_points, penalty_strength)
    fluid_density, viscosity : ρ (kg/m³), μ (Pa s)
    """

    def __init__(self, mesh, bodies, section, fluid_density: float, viscosity: float):
        self.mesh, self.comm, self.bodies = mesh, mesh.comm, bodies
        self.rho = float(fluid_density)
        self.nu = float(viscosity) / self.rho
        self.strength = float(section.penalty_strength)
        self.samples = reference_samples(mesh.cell_type, int(section.subcell_points))
        self.h2 = mesh.cell_volume[:mesh.n_owned_cells] ** (2 / 3)

    def begin(self, time: float, u: np.ndarray) -> BodyPasses:
        """Collective. The cells each body covers at ``time`` (the step's end), their rates and the
        bodies' velocity there; the blockage follows the largest |u − U| each body meets."""
        n_owned = self.mesh.n_owned_cells
        cells, owners, alphas = [], [], []
        for index, body in enumerate(self.bodies):
            cell, alpha = body.covered_cells(self.mesh, time, self.samples)
            cells.append(cell)
            owners.append(np.full(len(cell), index))
            alphas.append(alpha)
        cell, owner, alpha = np.concatenate(cells), np.concatenate(owners), np.concatenate(alphas)
        centre = self.mesh.cell_center[cell]
        rigid = np.zeros((len(cell), 3))
        for index, body in enumerate(self.bodies):
            rigid[owner == index] = body.velocity_at(centre[owner == index], time)
        speed = np.zeros(len(self.bodies))
        np.maximum.at(speed, owner, np.linalg.norm(u[cell] - rigid, axis=1))
        if self.comm.size > 1:
            self.comm.Allreduce(MPI.IN_PLACE, speed, op=MPI.MAX)
        total = np.bincount(cell, alpha, minlength=n_owned)[cell]
        kappa = cell_rate(np.minimum(total, 1.0), speed[owner], self.nu, self.h2[cell], self.strength) \
            * alpha / np.maximum(total, 1e-300)
        return BodyPasses(cell, owner, alpha, kappa, rigid)

    def implicit_terms(self, passes: BodyPasses):
        """Local. (V κ (n_owned,), V κ U (n_owned, 3)) of the bodies' penalty, per owned cell."""
        n_owned = self.mesh.n_owned_cells
        weight = self.mesh.cell_volume[passes.cell] * passes.kappa
        return np.bincount(passes.cell, weight, minlength=n_owned), sum_rows(passes.cell, weight[:, None] * passes.rigid,
                                                                               n_owned)

    def forces(self, passes: BodyPasses, u: np.ndarray, time: float) -> np.ndarray:
        """Collective. (n_bodies, 6): the force (N) the fluid exerts on each body, Σ ρ V κ (u − U) at
        the projected ``u``, and its torque (N m) about the body's rotation centre at ``time``."""
        force = (self.rho * self.mesh.cell_volume[passes.cell] * passes.kappa)[:, None] * (u[passes.cell] - passes.rigid)
        centre = np.array([b.rotation_center + b.velocity * time for b in self.bodies])
        arm = self.mesh.cell_center[passes.cell] - centre[passes.body]
        n = len(self.bodies)
        totals = np.column_stack([sum_rows(passes.body, force, n), sum_rows(passes.body, np.cross(arm, force), n)])
        if self.comm.size > 1:
            self.comm.Allreduce(MPI.IN_PLACE, totals, op=MPI.SUM)
        return totals

    def volume_fraction(self, passes: BodyPasses) -> np.ndarray:
        """(n_owned,) the bodies' volume fraction per owned cell."""
        return np.bincount(passes.cell, passes.alpha, minlength=self.mesh.n_owned_cells)
