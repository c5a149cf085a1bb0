"""Hard-sphere contacts (paper eq. 3-8) with walls, friction, rolling friction and deposition.

One compiled contact engine for every regime, laid out by stage:

- ``settings``       coefficients, limits, tolerances (``CollisionSettings``, ``collision_settings``)
- ``walls``          wall triangles, their motion and search (``Walls``, ``build_walls``)
- ``search``         broad search (``cell_list``, ``wall_grid``) → ``record.ContactRecord`` (the
                     step's contacts as arrays)
- ``narrow``         compiled narrow phase: gaps, normals, contact times of the candidates
- ``contact_times``  compiled contact times (eq. 5-7) and triangle geometry
- ``impulses``       compiled impulses: closed-form impact, Gauss–Seidel sweeps, rolling friction,
                     overlap removal
- ``events``         compiled time-ordered schedule of a step with few contacts (``event_queue``)
- ``dense``          a step with many contacts (a bed, a hopper): all at once
- ``subdomains``     the engine over the particles a rank owns; ``block``: its sweeps over the ranks,
                     compiled with their messages (``messages``: MPI's calls from compiled code)
- ``deposition``     compiled deposition zones
- ``record``         ``ContactRecord`` and ``ContactMemory`` (impulses kept between steps)
- ``solver``         ``advance_with_collisions``: one step, every regime
- ``wall_grid``      compiled uniform grid of the wall triangles (which are near a point)
- ``checks``         checks of new particles; ``jit`` loads the compiled modules on first use

docs/collisions.md states what the engine guarantees and what a step costs.
"""
from .checks import check_initial_particles, overlaps_existing
from .record import ContactMemory, ContactRecord
from .settings import CollisionSettings, collision_coefficients, collision_settings
from .solver import ContactStep, advance_with_collisions, closing_pairs, contact_impulse, projected_gauss_seidel
from .walls import Walls, build_walls, closest_points_on_triangles, wall_distances

__all__ = ["CollisionSettings", "ContactMemory", "ContactRecord", "ContactStep", "Walls", "advance_with_collisions",
           "build_walls", "check_initial_particles", "closest_points_on_triangles", "closing_pairs",
           "collision_coefficients", "collision_settings", "contact_impulse", "overlaps_existing",
           "projected_gauss_seidel", "wall_distances"]

