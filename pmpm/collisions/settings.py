"""The contact engine's coefficients, limits and tolerances (one place for every number it uses)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DEFAULT_RESTITUTION, DEFAULT_FRICTION, DEFAULT_ROLLING_FRICTION = 0.9, 0.3, 0.0

# Relative tolerances, all dimensionless.
APPROACH_TOL = 1e-9   # approach speeds below 1e-9 |u| are round-off, not contacts
TOUCH_TOL = 1e-9      # spheres this close (relative to the contact distance) touch: a time-0 impact
CONTACT_TOL = 1e-6    # resting contacts: gap <= 1e-6 r at the start of a solve
GAP_TOL = 1e-7        # a predicted wall contact further than 1e-7 r (a rotating wall's linearised path) is rescheduled
QUIET = 1e-3          # × rest_speed: touching contacts approaching slower are left to the next step's resting solve
PARALLEL = 1 - 1e-4   # wall contacts of one particle with normals closer than ~0.8° count as one
OVERLAP_TOL = 1e-9    # × (r_i + r_j): overlaps beyond this are removed by moving positions (never velocities)
SWEEP_TOL = 1e-10     # × rest_speed: a solve ends with a sweep that changes no contact-point velocity by more
ENERGY_TOL = 1e-12    # relative: a contact solve may not raise the kinetic energy by more (round-off)
SEARCH_SLACK = 1.25   # the broad search assumes speeds up to 1.25 × the fastest (then, if outgrown, the speed seen)
SEPARATION_SWEEPS = 50  # sweeps of an overlap removal after an event step (a fifth after a dense step)
MAX_SEARCHES = 3      # the step is searched at most this often (then contacts beyond the search are left
                      # to the next step, as overlaps)


@dataclass(frozen=True)
class CollisionSettings:
    """Particle–particle coefficients and the engine's limits.

    ``rest_speed`` (m/s): contacts approaching slower than this are resting contacts, solved together
    and inelastically (e = 0); 0 turns the resting solve off (every contact is an impact).
    ``max_events_per_particle``: the impacts of one step are at most this × the particle count (at
    least ``min_events``); past it the step ends with every touching contact made inelastic.
    ``dense_contacts``: a step with at least this many contacts (touching, or able to close within
    the step) is a dense step: every contact solved at once, impacts with their restitution, no
    events; 0 never. ``dense_sweeps``: the most sweeps of a warm-started dense step (× 20 cold).
    ``resting_sweeps``: the most sweeps of the resting solve at a step's start (warm-started, tightly
    converged); ``settle_sweeps``: of one after a slow impact inside the step (cold; what it leaves
    undone the next step's resting solve finishes). ``gather_contacts``: where ranks own particles,
    a step with fewer contacts that can act, over all ranks, gathers the particles in contact and
    solves them as one rank does (``subdomains``); 0 never.
    """

    restitution: float = DEFAULT_RESTITUTION
    friction: float = DEFAULT_FRICTION
    rolling_friction: float = DEFAULT_ROLLING_FRICTION
    rest_speed: float = 0.0
    max_events_per_particle: int = 50
    min_events: int = 1000
    dense_contacts: int = 256
    dense_sweeps: int = 20
    resting_sweeps: int = 100
    settle_sweeps: int = 50
    gather_contacts: int = 4096


COLD_SWEEPS = 20  # × dense_sweeps for a dense step without any remembered impulse


def collision_coefficients(case) -> dict:
    """restitution, friction, rolling_friction of [collisions] (the defaults without it)."""
    section = getattr(case, "collisions", None)
    if section is None:
        return {"restitution": DEFAULT_RESTITUTION, "friction": DEFAULT_FRICTION,
                "rolling_friction": DEFAULT_ROLLING_FRICTION}
    return {"restitution": section.restitution, "friction": section.friction,
            "rolling_friction": section.rolling_friction}


def collision_settings(case) -> CollisionSettings:
    """Settings from [collisions] and [run]: rest speed 3 |g| dt (dt per particle substep)."""
    coefficients = collision_coefficients(case)
    substeps = case.coupling.substeps if getattr(case, "coupling", None) is not None else 1
    g = float(np.linalg.norm(case.run.gravity))
    rest = 3.0 * g * case.run.dt / substeps
    section = getattr(case, "collisions", None)   # (absent keys: the dataclass's defaults)
    limits = {name: getattr(section, name) for name in ("dense_sweeps", "gather_contacts") if hasattr(section, name)}
    return CollisionSettings(**coefficients, rest_speed=rest if rest > 0 else 1e-9, **limits)
