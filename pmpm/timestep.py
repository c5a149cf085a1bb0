"""The time step's size and the flow's health between steps: the adaptive step (``[run]
adaptive_cfl``) and the CFL watch that warns, keeps the last good state and stops a diverging run.
Both take the built pieces (``simulation.Model``) and the run state; neither keeps anything."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from mpi4py import MPI

from . import reporting
from .errors import NumericalError
from .state import RunState

if TYPE_CHECKING:   # annotations only: nothing imports the simulation at run time
    from .simulation import Model


GROWTH = 1.25   # an adaptive step grows only when it can grow by this factor (fewer changes of the
                # momentum matrices' diagonal and the pressure's tolerance)
FIRST_STEP_SPEEDUP = 4.0   # the first step of a flow from rest: how much faster than its boundaries it may be


def next_time_step(model: Model, state: RunState, until: float) -> float:
    """Collective (adaptive). The size of the next step: [run] dt (the last step shorter, to end at
    end_time); or, with [run] adaptive_cfl c, the largest dt ≤ [run] dt that keeps the flow's CFL
    number at c and the particles' travel per step at c cells (without a flow: c radii), changed
    only when it must shrink or can grow by GROWTH (at most doubling), and never past ``until``
    (the next output, checkpoint or the end), which it reaches in two even steps rather than a
    long one and a sliver. The first step of a flow from rest takes a quarter of the boundary
    speeds' limit: the ventilated box's first flow met 2.7 × its inlet speed at the outlet's edge."""
    run = model.case.run
    if not run.adaptive_cfl:
        return min(run.dt, run.end_time - state.time)
    limit, target = run.dt, run.adaptive_cfl
    length = float(state.particles.radius.min(initial=np.inf))
    if model.flow is not None:
        flow = model.flow
        h = float(flow.h[:model.mesh.n_owned_cells].min(initial=np.inf))
        speed = float(np.linalg.norm(flow.u_fixed, axis=1).max(initial=0.0))
        rate = max(float(flow.convective_rates(state.fluid).max(initial=0.0)), speed / h)
        rate, length = model.comm.allreduce(rate, op=MPI.MAX), model.comm.allreduce(h, op=MPI.MIN)
        if state.step == 0:   # the first projection's potential flow outruns the boundary speeds at corners
            rate *= FIRST_STEP_SPEEDUP
        limit = min(limit, target / rate) if rate > 0 else limit
    speed = float(np.linalg.norm(state.particles.v, axis=1).max(initial=0.0))
    if state.partition is not None:
        speed = model.comm.allreduce(speed, op=MPI.MAX)
        if model.flow is None:
            length = model.comm.allreduce(length, op=MPI.MIN)
    if speed > 0:
        limit = min(limit, target * length / speed)
    last = state.dt
    dt = limit
    if 0 < last <= limit:
        dt = last if limit < GROWTH * last else min(limit, 2 * last)
    left = until - state.time
    if dt >= left * (1 - 1e-9):
        return left
    return left / 2 if dt > left / 2 else dt


@dataclass(frozen=True)
class FlowWatch:
    """What the run keeps to judge the flow: the latest state whose CFL number was within the
    stable range (written if the flow diverges later), the largest CFL number of such states and
    the boundary velocities', and whether the run has warned of a large one (and of one in a step
    where injected particles displaced their volume)."""

    good: RunState
    stable_cfl: float = 0.0
    warned: bool = False
    warned_displacing: bool = False


STABLE_CFL = 2.0      # × [run] max_cfl: a state below it is kept as the last good one
DIVERGED_CFL = 10.0   # × [run] max_cfl: above it the explicit convection is blowing up: stop


def watch_flow(model: Model, state: RunState, dt: float, watch: FlowWatch,
               displacing: bool = False) -> FlowWatch:
    """Collective (with a flow). The CFL number after a step: warned of above [run] max_cfl, kept
    as the last good state below STABLE_CFL × max_cfl, and above DIVERGED_CFL × max_cfl (or not
    finite) the run stops: NumericalError naming the step, time, cell and remedy. In a step where
    newly injected particles displaced their volume (``displacing``) the warning says so: that
    outflow lasts one step and its CFL number, about volume / (area × h), does not fall with dt."""
    if model.flow is None:
        return replace(watch, good=state)
    limit = model.case.run.max_cfl
    cfl, where = model.flow.largest_cfl(state.fluid, dt)
    if cfl > DIVERGED_CFL * limit:
        good = watch.good
        suggestion = dt * limit / max(watch.stable_cfl, limit)
        raise NumericalError(
            f"step {state.step}, t = {state.time:.6g} s: the flow is diverging: CFL number {cfl:.3g} in the cell "
            f"at ({where[0]:.4g}, {where[1]:.4g}, {where[2]:.4g}) (stopped above {DIVERGED_CFL * limit:g}); "
            f"reduce [run] dt (to {suggestion:.3g} s or less) or use convection = \"upwind\"; written: the last "
            f"state with CFL ≤ {STABLE_CFL * limit:g}, step {good.step}, t = {good.time:.6g} s")
    if cfl > limit and displacing:
        if not watch.warned_displacing:
            reporting.warn_once(model.comm, f"step {state.step}: CFL number {cfl:.2f} in the cell at ({where[0]:.4g}, "
                                            f"{where[1]:.4g}, {where[2]:.4g}) exceeds [run] max_cfl = {limit:g} in a "
                                            "step where injected particles displace their volume of fluid: that "
                                            "outflow lasts one step, and a smaller dt does not lower its CFL number "
                                            "(docs/coupling.md)")
            watch = replace(watch, warned_displacing=True)
    elif cfl > limit and not watch.warned:
        reporting.warn_once(model.comm, f"step {state.step}: CFL number {cfl:.2f} in the cell at ({where[0]:.4g}, "
                                        f"{where[1]:.4g}, {where[2]:.4g}) exceeds [run] max_cfl = {limit:g}; the "
                                        "explicit convection may go unstable: reduce [run] dt")
        watch = replace(watch, warned=True)
    if cfl <= STABLE_CFL * limit:
        watch = replace(watch, good=state, stable_cfl=max(watch.stable_cfl, cfl))
    return watch
