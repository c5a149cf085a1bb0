"""Big particles in the flow (paper eq. 1–2, Figure 1): touched cells, volume fractions, the
forcing that drives the fluid in them towards the particles' rigid motion, drag and torque.

A cell is *touched* by a particle when one of its vertices lies in the sphere, and carries the
particle's volume fraction α (``locate``). The fluid there is driven towards U = V + ω × r, and the
momentum this takes from the particle is its drag and torque (r × F, r from the centre to the cell
centre). Two forcings (``[coupling] forcing``), one class each with the same stages, chosen once
when the case is built (``build_forcing``):

- ``PenaltyForcing`` (default, ``penalty.py``): an implicit penalty solved with the diffusion;
- ``PatchForcing`` (the paper, ``patch.py``): u ← (1 − α) u + α U after each solve.

The time loop (``pmpm.flow_stage.flow_stage``) calls, in this order, each a value in, a value out:

    touched = forcing.locate(particles)                           local
    passes, fluid = forcing.begin(particles, touched, fluid, memory, dt, holders)
    per forcing pass:
        diagonal, target = forcing.implicit_terms(particles, passes)      → the momentum solve
        u_star, source, passes = forcing.after_solve(particles, passes, u_star, external, dt)
        (source: momentum the forcing added to u*, for the right-hand side of a next solve)
    exchange = forcing.after_projection(particles, passes, fluid, external, dt, memory, step, time)

``passes`` carries the step's state from stage to stage; ``memory`` (``CouplingMemory``) what the
coupling carries to the next step. The particle update (``[coupling] update``, implicit or
explicit) is in ``update.py``. Parallel: each rank sums over its owned cells only, for its own
particles and ghost copies of those that reach into its cells; the per-particle sums meet among
each particle's holders (``holders.py``, ``sums.py``), and every holder applies the same update to
its copy. docs/coupling.md has the method's measurements.
"""
from __future__ import annotations

import numpy as np

from .correction import DragCorrection
from .locate import CellLocator, Touched, alpha_per_cell, shared_alpha, shared_smooth, volume_fraction
from .memory import CouplingMemory
from .patch import PatchForcing
from .penalty import PenaltyForcing
from .update import Exchange, External

__all__ = ["CellLocator", "CouplingMemory", "DragCorrection", "Exchange", "External", "PatchForcing", "PenaltyForcing",
           "Touched", "alpha_per_cell", "build_forcing", "shared_alpha", "shared_smooth", "volume_fraction"]


def build_forcing(mesh, section, fluid, diameter: float = 0.0) -> PenaltyForcing | PatchForcing:
    """The forcing the case's [coupling] section asks for, on ``mesh``, for the [fluid] ``fluid``;
    ``diameter``: the largest particle diameter of the case (m), which sets the drag correction's
    default filter width."""
    if section.forcing == "penalty":
        correction = None
        if section.drag_correction != "off":
            width = section.correction_filter or 3.0 * diameter
            correction = DragCorrection(mesh, section.drag_correction, width if width > 0 else np.inf,
                                        fluid.density, fluid.viscosity)
        return PenaltyForcing(mesh, section, fluid.density, fluid.viscosity, correction)
    return PatchForcing(mesh, section, fluid.density)
