"""The run state: everything a run carries from one time step to the next, as one value.

The stages of a step (``pmpm.simulation``) take a ``RunState`` and return a new one; none changes
the arrays of the state it was given. So the time loop keeps the state a step started from by
reference, and writes it if the step fails; and ``pmpm.checkpoint`` writes and reads it whole.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .arrays import members
from .collisions import ContactMemory, Walls
from .coupling import CouplingMemory
from .fluid import FluidState
from .ownership import Partition
from .particles import ParticleState


@dataclass(frozen=True)
class RunState:
    """One moment of a run (SI).

    time, step : simulated time (s) and steps taken; dt : the last step's size (s)
    particles : every particle (``pmpm.particles``); with ``partition``, the particles this rank owns
    partition : the ranks' boxes (``pmpm.ownership``) where particles are owned by ranks (several
        ranks; without a flow bisected over the particles, with one the mesh's), else None
    fluid : the flow, or None without [fluid]
    hydro_force, hydro_torque : (n, 3) the fluid's force (N) and torque (N m) on each particle over the
        last step (zero where no flow acted yet)
    volume_fraction : (n_local,) the particles' volume fraction per cell in the last step, or None
    next_id : the id the next new particle gets (ids are never reused)
    removed : particles that have left the domain; removed_through : how many through each boundary
        (name → count; ``pmpm.exits``)
    releases : per [[injection]], the index of its next release; injection_counts : the releases'
        particles placed at once, placed after retries, and dropped, summed over the run
    fresh_from : particles with this id or larger were released at the end of the last step and
        have not met the flow yet (they displace their volume of fluid in the next step)
    coupling : the coupling's memory (``pmpm.coupling.CouplingMemory``), or None without [fluid]
    contacts : the contact solver's memory (``pmpm.collisions.ContactMemory``), or None
    walls : the wall triangles as they are now (rigid walls move), or None when no model needs them
    collision_totals : collision counts summed over the run (``pmpm.collisions``)
    pressure_iterations : pressure KSP iterations summed over the run
    body_forces : (n_bodies, 6) the fluid's force (N) and torque (N m) on each [[body]] over the last
        step, or None
    ranks_seen : where particles are owned by ranks, the largest number of owned and of ghost
        particles this rank held in a contact step and the most bytes it sent in one (``owned``,
        ``ghosts``, ``exchanged_bytes``; reduced over ranks for summary.json)
    """

    time: float
    step: int
    particles: ParticleState
    fluid: FluidState | None
    hydro_force: np.ndarray
    hydro_torque: np.ndarray
    volume_fraction: np.ndarray | None
    next_id: int
    removed: int
    releases: tuple[int, ...]
    dt: float = 0.0
    fresh_from: int = 0
    injection_counts: dict = field(default_factory=dict)
    removed_through: dict = field(default_factory=dict)
    coupling: CouplingMemory | None = None
    contacts: ContactMemory | None = None
    walls: Walls | None = None
    collision_totals: dict = field(default_factory=dict)
    pressure_iterations: int = 0
    body_forces: np.ndarray | None = None
    partition: Partition | None = None
    ranks_seen: dict = field(default_factory=dict)

    @property
    def n_global_particles(self) -> int:
        """The particles of the run on every rank together (ids are given once, removals counted)."""
        return self.next_id - self.removed

    def owned_by(self, rank: int, partition: Partition) -> "RunState":
        """This state, whose particles every rank holds whole (the case's, a checkpoint's), as rank
        ``rank``'s share in the boxes of ``partition``: its particles and the contact memory of the
        contacts whose lower-id particle it owns."""
        particles = self.particles
        mine = partition.owner_of(particles.x) == rank
        contacts = self.contacts
        if contacts is not None:
            contacts = contacts.take(members(contacts.first_id, particles.id[mine]))
        return replace(self, particles=particles.without(~mine), hydro_force=self.hydro_force[mine],
                       hydro_torque=self.hydro_torque[mine], contacts=contacts, partition=partition)
