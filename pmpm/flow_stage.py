"""Steps 2–5 of a time step with a flow (``flow_stage``): the particles' touched cells, the flow
advanced with their forcing, the projection, the fluid's force and torque on each particle and on
each immersed body. ``pmpm.simulation.advance`` calls it; the forcing's stages are in
``pmpm.coupling`` (its docstring lists them in order).
"""
from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from .arrays import summed
from .coupling import External, volume_fraction
from .coupling.holders import Holders
from .halo import Halo
from .particles import ParticleState
from .reporting import StageTimes
from .state import RunState

if TYPE_CHECKING:   # (simulation imports this module)
    from .simulation import Model


def flow_stage(model: Model, state: RunState, external: External, dt: float, times: StageTimes) -> RunState:
    """Collective. Steps 2–5: the particles' touched cells, the flow advanced with their forcing
    (``forcing_passes`` momentum solves, the forcing updating its guess of the particles' motion
    after each), the projection, and the fluid's force and torque on each particle; the bodies'
    prescribed motion enters the same solves, and the fluid's force on each body comes out.
    Particles injected in the last step (ids from ``state.fresh_from``) displace their volume of
    fluid, which the projection makes leave through the outlets. Where ranks own particles, each
    works on its own and ghost copies of those that reach into its cells (``held_for_the_flow``)."""
    flow, forcing, bodies = model.flow, model.forcing, model.body_forcing
    n_owned = model.mesh.n_owned_cells
    step, time = state.step, state.time
    coupled = state.n_global_particles > 0   # (the same on every rank)
    passes = model.case.coupling.forcing_passes if coupled else 1
    fluid = state.fluid
    with times.stage("coupling"):
        particles, holders, external, state = held_for_the_flow(model, state, external)
        touched = forcing.locate(particles)
        injected = particles.id >= state.fresh_from if state.next_id > state.fresh_from else None
        displaced = displaced_volume(model, particles, touched, injected, dt, holders)
        if coupled:
            forcing_state, fluid = forcing.begin(particles, touched, fluid, state.coupling, dt, holders)
        if bodies is not None:   # where the bodies are at the step's end, moving as prescribed
            body_state = bodies.begin(time + dt, fluid.u)
            body_diagonal, body_target = bodies.implicit_terms(body_state)
    with times.stage("flow"):
        predicted = flow.predictor(fluid, dt)
    rhs, u_star = predicted.rhs, fluid.u
    for forcing_pass in range(passes):
        diagonal = target = None
        if coupled:
            with times.stage("coupling"):
                diagonal, target = forcing.implicit_terms(particles, forcing_state)
        if bodies is not None:
            diagonal = body_diagonal if diagonal is None else diagonal + body_diagonal
            target = body_target if target is None else target + body_target
        with times.stage("flow"):
            u_star = flow.solve_momentum(rhs if target is None else plus_owned(rhs, target), u_star, dt, step, time,
                                         extra_diagonal=diagonal)
        if coupled:
            with times.stage("coupling"):
                u_star, source, forcing_state = forcing.after_solve(particles, forcing_state, u_star, external, dt)
            if source is not None and forcing_pass < passes - 1:
                rhs = plus_owned(rhs, source)
    with times.stage("flow"):
        rate = None
        if diagonal is not None:   # the penalty of the last solve damps the pressure's terms in its cells
            rate = np.zeros(model.mesh.n_local_cells)
            rate[:n_owned] = diagonal / model.mesh.cell_volume[:n_owned]
            model.mesh.update_ghosts(rate)
        projection = flow.project(fluid, u_star, predicted, dt, step, time, volume_source=displaced, penalty_rate=rate)
        fluid = flow.correct(fluid, u_star, projection, dt, penalty_rate=rate)
    with times.stage("coupling"):
        fractions = np.zeros(model.mesh.n_local_cells)
        fractions[:n_owned] = volume_fraction(touched, n_owned)
        if bodies is not None:
            fractions[:n_owned] = np.minimum(fractions[:n_owned] + bodies.volume_fraction(body_state), 1.0)
            state = replace(state, body_forces=bodies.forces(body_state, fluid.u, time + dt))
        state = replace(state, fluid=fluid, volume_fraction=fractions,
                        pressure_iterations=state.pressure_iterations + projection.iterations)
        if coupled:
            exchange = forcing.after_projection(particles, forcing_state, fluid, external, dt, state.coupling,
                                                step, time)
            owned = holders.owned
            state = replace(state, fluid=exchange.fluid, hydro_force=exchange.force[owned],
                            hydro_torque=exchange.torque[owned], coupling=exchange.memory)
    flow.check(state.fluid, step, time)
    return state


def held_for_the_flow(model: Model, state: RunState, external: External):
    """Collective. The particles this rank works on in the flow stage, where their per-particle
    sums meet (``coupling.holders.Holders``), and their external forces: every particle where every
    rank holds them; where ranks own particles, its own and ghost copies of every particle whose
    sphere, with the forcing's reach, comes within this rank's cells (the owners' external forces
    copied to them). Returns (particles, holders, external, state: its ``ranks_seen`` counting them)."""
    if state.partition is None:
        return state.particles, Holders.everywhere(model.comm, len(state.particles)), external, state
    owned = state.particles
    halo, local = Halo.build(model.comm, model.cell_boxes, owned, (owned.radius + model.coupling_reach) * (1 + 1e-9))
    force, torque = np.zeros((len(local), 3)), np.zeros((len(local), 3))
    force[halo.owned], torque[halo.owned] = external.force, external.torque
    halo.to_ghosts(force, torque)
    seen = {**state.ranks_seen, "owned": max(state.ranks_seen.get("owned", 0), len(owned)),
            "ghosts": max(state.ranks_seen.get("ghosts", 0), len(local) - len(owned))}
    return local, Holders(model.comm, halo, halo.owned), External(force, torque), replace(state, ranks_seen=seen)


def displaced_volume(model: Model, particles: ParticleState, touched, injected: np.ndarray | None, dt: float,
                     holders: Holders) -> np.ndarray | None:
    """Collective (when particles were injected). The paper's mass source for continuous
    injection, (n_local,) m³/s: each particle ``injected`` in the last step (bool per particle;
    None, the same on every rank, where none was) displaces its volume of fluid within this step,
    shared among the cells it covers by their α V; None when none was."""
    if injected is None:
        return None
    mesh = model.mesh
    new = injected[touched.particle]
    p, c = touched.particle[new], touched.cell[new]
    covered = touched.alpha[new] * mesh.cell_volume[c]
    per_particle = holders.sum(summed(p, covered, len(particles)))
    share = covered / np.maximum(per_particle[p], np.finfo(float).tiny)
    source = np.zeros(mesh.n_local_cells)
    source[:mesh.n_owned_cells] = np.bincount(c, share * particles.volume[p] / dt, minlength=mesh.n_owned_cells)
    return source


def plus_owned(array: np.ndarray, owned_rows: np.ndarray) -> np.ndarray:
    """A copy of ``array`` with ``owned_rows`` added to its first rows (the owned cells')."""
    out = array.copy()
    out[:len(owned_rows)] += owned_rows
    return out
