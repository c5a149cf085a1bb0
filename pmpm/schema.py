"""Every case key, declared once: its section, TOML type, default, check and unit (``SCHEMA``).

The parser (``pmpm.case``), the ``--set`` overrides, the error messages and the key table in
docs/case_keys.md (``tools/case_keys.py``) all read these declarations.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

REQUIRED = object()  # marks a key without a default
# most intervals of [run] end_time that the time loop may count: a step of dt stays 1000 units
# in the last place of the time, so time keeps advancing (2^52 / 1000)
MAX_STEPS = 2.0 ** 52 / 1000


@dataclass(frozen=True)
class Key:
    """One case key: its TOML type, default, allowed values and unit."""

    name: str
    kind: str  # float | int | bool | str | vec3 | ivec3 | strings
    default: Any = REQUIRED
    check: str = ""  # ">0", ">=0", "0..1", "(0,1)" (both ends excluded), or "" (none)
    choices: tuple = ()
    unit: str = ""
    help: str = ""


# ----------------------------------------------------------------------------------------------
# The schema: section → keys. Tables with user-chosen names (boundary.<name>) and arrays of
# tables (particles.add, injection) are declared the same way and handled by the parser.
# ----------------------------------------------------------------------------------------------
SCHEMA: dict[str, tuple[Key, ...]] = {
    "run": (
        Key("end_time", "float", check=">0", unit="s", help="simulated time to reach"),
        Key("dt", "float", check=">0", unit="s", help="time step (of the flow, when one is solved)"),
        Key("output_every", "float", None, ">0", unit="s", help="simulated seconds between outputs (default: 20 outputs)"),
        Key("checkpoint_every", "float", None, ">0", unit="s", help="simulated seconds between checkpoints (default: none)"),
        Key("gravity", "vec3", (0.0, 0.0, -9.81), unit="m/s²"),
        Key("seed", "int", 1, ">=0", help="every random choice derives from it"),
        Key("max_cfl", "float", 1.0, ">0", help="warn when the flow's CFL number exceeds it"),
        Key("adaptive_cfl", "float", 0.0, ">=0",
            help="adaptive time step: each step the largest dt <= [run] dt that keeps the flow's CFL number, "
                 "and the particles' travel in cells, at this value (0: a fixed dt)"),
        Key("wall_time_limit", "float", 0.0, ">=0", unit="s", help="stop cleanly after this wall time (0: none)"),
    ),
    "mesh": (
        Key("file", "str", None, help="mesh file: gmsh .msh or any format meshio reads"),
        Key("cell_type", "str", "hex", choices=("hex", "tet"), help="box cells: hexahedra or tetrahedra"),
    ),
    "mesh.patch": (
        Key("name", "str", help="the boundary name of the faces it covers ([boundary.<name>] sets its type)"),
        Key("side", "str", choices=("xmin", "xmax", "ymin", "ymax", "zmin", "zmax"), help="the box's side it lies on"),
        Key("lower", "vec3", unit="m", help="the faces of the side whose centres lie in [lower, upper]"),
        Key("upper", "vec3", unit="m"),
    ),
    "mesh.box": (
        Key("lower", "vec3", unit="m"),
        Key("upper", "vec3", unit="m"),
        Key("cells", "ivec3", check=">0"),
    ),
    "fluid": (
        Key("density", "float", check=">0", unit="kg/m³"),
        Key("viscosity", "float", check=">0", unit="Pa s", help="dynamic viscosity"),
        Key("convection", "str", "linear_upwind", choices=("upwind", "linear_upwind", "central"),
            help="face interpolation of the convected velocity"),
        Key("pressure_rtol", "float", 1e-8, "(0,1)", help="relative tolerance of the pressure solve"),
        Key("nonorthogonal_correctors", "int", 1, ">=0", help="extra pressure solves on skewed meshes"),
    ),
    "boundary.*": (
        Key("type", "str", "wall", choices=("wall", "inlet", "outlet", "symmetry")),
        Key("velocity", "vec3", (0.0, 0.0, 0.0), unit="m/s", help="inlet velocity, or a wall's translation"),
        Key("angular_velocity", "vec3", (0.0, 0.0, 0.0), unit="rad/s", help="a wall's rotation"),
        Key("center", "vec3", (0.0, 0.0, 0.0), unit="m", help="a wall's rotation centre"),
        Key("motion", "str", "surface", choices=("surface", "rigid"),
            help="surface: the wall stays, its surface moves (a lid, a spinning drum); rigid: the wall "
                 "itself moves (a paddle; particles-only scenes)"),
        Key("pressure", "float", 0.0, unit="Pa", help="outlet pressure"),
        Key("particles", "str", None, choices=("wall", "pass"),
            help="how particles meet the boundary: wall, they bounce off it (the default for walls, inlets — a "
                 "distributor plate — and symmetry planes), or pass, they leave the domain (the default for outlets)"),
        Key("restitution", "float", None, "0..1", help="overrides [collisions] for this wall"),
        Key("friction", "float", None, ">=0", help="overrides [collisions] for this wall"),
        Key("rolling_friction", "float", None, ">=0", help="overrides [collisions] for this wall"),
    ),
    "coupling": (
        Key("mode", "str", "two-way", choices=("two-way", "one-way")),
        Key("volume_fraction", "str", "nodes", choices=("nodes", "subcell"),
            help="nodes: the paper's share of cell vertices inside; subcell: k³ sample points"),
        Key("subcell_points", "int", 4, ">0", help="k for volume_fraction = subcell"),
        Key("substeps", "int", 1, ">0", help="particle substeps per flow step"),
        Key("forcing_passes", "int", 3, ">0",
            help="patch-and-diffuse passes per step (multi-direct forcing; 1: the paper's single patch)"),
        Key("forcing", "str", "penalty", choices=("penalty", "patch"),
            help="penalty: κ(α)(U − u) solved with the diffusion, forces independent of dt; patch: the "
                 "paper's α-weighted patch after each solve (forces depend on ν dt/h², docs/coupling.md)"),
        Key("penalty_strength", "float", 35.0, ">0",
            help="s in the penalty's friction rate s α/(1 − α) ν/h² of a cell with volume fraction α (its "
                 "blockage rate, (1000/6) α⁸ U_rel/h with U_rel the flow's speed past the particle, has no knob; "
                 "docs/coupling.md)"),
        Key("update", "str", "implicit", choices=("implicit", "explicit"),
            help="implicit: stable for light particles (measured to ρp/ρf = 0.3); explicit: the paper's, "
                 "rings below ρp/ρf ≈ 0.5–1.2 (docs/coupling.md)"),
        Key("drag_correction", "str", "off", choices=("off", "di_felice", "di_felice_standard", "beetstra"),
            help="particles on a few cells per diameter: bring their drag to Di Felice's (1994) correlation, "
                 "the same on the standard drag curve of a lone sphere (di_felice_standard), or Beetstra et al.'s "
                 "(2007), at the local voidage, raising it where the resolved drag falls short (dense beds) and "
                 "taking off the excess above Re = (d/h)², where the boundary layer is thinner than a cell "
                 "(penalty forcing, two-way; docs/coupling.md, \"Dense suspensions\")"),
        Key("correction_filter", "float", None, ">0", unit="m",
            help="drag_correction: the width of the box over which each particle's voidage and slip are averaged "
                 "(default: 3 × the largest particle diameter of the case)"),
    ),
    "particles": (
        Key("file", "str", None, help="ASCII particle file: x y z [vx vy vz wx wy wz] radius density"),
    ),
    "particles.add": (
        Key("position", "vec3", unit="m"),
        Key("velocity", "vec3", (0.0, 0.0, 0.0), unit="m/s"),
        Key("angular_velocity", "vec3", (0.0, 0.0, 0.0), unit="rad/s"),
        Key("radius", "float", check=">0", unit="m"),
        Key("density", "float", check=">0", unit="kg/m³"),
        Key("motion", "str", "free", choices=("free", "fixed", "prescribed")),
    ),
    "collisions": (
        Key("restitution", "float", 0.9, "0..1"),
        Key("friction", "float", 0.3, ">=0", help="Coulomb friction coefficient"),
        Key("rolling_friction", "float", 0.0, ">=0", help="rolling (and spin) resistance coefficient at walls"),
        Key("dense_sweeps", "int", 20, ">0",
            help="the most projected Gauss-Seidel sweeps of a dense step (a bed, a hopper), on any number of ranks "
                 "(docs/collisions.md, \"Accuracy on several ranks\")"),
        Key("gather_contacts", "int", 4096, ">=0",
            help="without a fluid, on several ranks: steps with fewer contacts over all ranks are solved as on "
                 "one rank (the contacts' particles gathered), larger ones by block Gauss-Seidel over the ranks"),
    ),
    "field_forces": (
        Key("G_p", "float", 0.0, help="eq. 9: > 0 attracts, < 0 repels"),
        Key("n1", "float", 1.0), Key("n2", "float", 1.0), Key("n3", "float", 2.0),
        Key("G_w", "float", 0.0, help="eq. 10: > 0 attracts, < 0 repels"),
        Key("n4", "float", 1.0), Key("n5", "float", 2.0),
        Key("cutoff", "float", None, ">0", unit="m", help="interaction range (default: 5 mean diameters)"),
    ),
    "injection": (
        Key("kind", "str", "point", choices=("point", "random", "cylindrical")),
        Key("start", "float", 0.0, ">=0", unit="s"),
        Key("stop", "float", math.inf, ">=0", unit="s"),
        Key("interval", "float", check=">0", unit="s"),
        Key("count", "int", 1, ">0", help="particles per release"),
        Key("position", "vec3", (0.0, 0.0, 0.0), unit="m"),
        Key("velocity", "vec3", (0.0, 0.0, 0.0), unit="m/s"),
        Key("angular_velocity", "vec3", (0.0, 0.0, 0.0), unit="rad/s"),
        Key("radius", "float", check=">0", unit="m"),
        Key("density", "float", check=">0", unit="kg/m³"),
        Key("lower", "vec3", None, unit="m", help="random: box of release points"),
        Key("upper", "vec3", None, unit="m"),
        Key("origin", "vec3", None, unit="m", help="cylindrical: origin of the frame"),
        Key("axis", "vec3", (0.0, 0.0, 1.0), help="cylindrical: axis direction"),
        Key("r", "float", 0.0, ">=0", unit="m"),
        Key("theta", "float", 0.0, unit="rad",
            help="cylindrical: angle about the axis from the reference direction, the global axis after the "
                 "axis's largest component in the order x → y → z → x (axis z: from +x towards +y)"),
        Key("z", "float", 0.0, unit="m"),
        Key("location_velocity", "vec3", (0.0, 0.0, 0.0), unit="m/s",
            help="moving injection location: the release point, velocity and spin move and turn with it, and "
                 "a particle leaves with the location's own velocity added"),
        Key("location_angular_velocity", "vec3", (0.0, 0.0, 0.0), unit="rad/s"),
        Key("rotation_center", "vec3", (0.0, 0.0, 0.0), unit="m"),
    ),
    "body": (
        Key("name", "str", None, help="how messages and summary.json name the body (default: body <n>)"),
        Key("shape", "str", check="", choices=("box", "cylinder", "surface"),
            help="box (axis-aligned at t = 0), cylinder, or a closed triangulated surface from a file"),
        Key("center", "vec3", (0.0, 0.0, 0.0), unit="m", help="box, cylinder: the centre at t = 0"),
        Key("size", "vec3", None, check=">0", unit="m", help="box: its edges along x, y, z (before tilt)"),
        Key("tilt", "vec3", (0.0, 0.0, 0.0), unit="rad",
            help="box, cylinder: turned about its centre at t = 0 by this rotation vector (a pitched blade, a slope)"),
        Key("axis", "vec3", (0.0, 0.0, 1.0), help="cylinder: its axis"),
        Key("radius", "float", None, ">0", unit="m", help="cylinder"),
        Key("length", "float", None, ">0", unit="m", help="cylinder: along its axis"),
        Key("file", "str", None, help="surface: a closed triangulated surface (STL, or any surface meshio reads)"),
        Key("velocity", "vec3", (0.0, 0.0, 0.0), unit="m/s", help="prescribed translation"),
        Key("angular_velocity", "vec3", (0.0, 0.0, 0.0), unit="rad/s",
            help="prescribed rotation about rotation_center (which moves with the translation)"),
        Key("rotation_center", "vec3", (0.0, 0.0, 0.0), unit="m"),
        Key("restitution", "float", None, "0..1", help="particles on the body (default: [collisions])"),
        Key("friction", "float", None, ">=0", help="particles on the body (default: [collisions])"),
        Key("rolling_friction", "float", None, ">=0", help="particles on the body (default: [collisions])"),
    ),
    "deposition": (
        Key("zones", "strings", (), help="wall boundaries on which particles stay"),
    ),
}
SECTIONS = ("run", "mesh", "fluid", "boundary", "coupling", "particles", "collisions",
            "field_forces", "injection", "body", "deposition")
ARRAY_TABLES = {"injection", "particles.add", "body", "mesh.patch"}
