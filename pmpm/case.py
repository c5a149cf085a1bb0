"""The case file: ``case.toml`` → one frozen dataclass per section.

Every key is declared once in ``pmpm.schema`` with its type, default, check and unit; this module
parses the file and the ``--set`` overrides against it, checks each value and the rules that
involve several keys (``check_consistency``). A section that is absent from the file stays
``None`` on the ``Case``: its model is switched off.
"""
from __future__ import annotations

import difflib
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from .errors import CaseError
from .schema import ARRAY_TABLES, MAX_STEPS, REQUIRED, SCHEMA, SECTIONS, Key


# ----------------------------------------------------------------------------------------------
# The typed case
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Section:
    """Values of one table, as attributes (``case.fluid.viscosity``)."""

    values: dict = field(default_factory=dict)

    def __getattr__(self, name):
        try:
            return self.values[name]
        except KeyError:
            raise AttributeError(name) from None


@dataclass(frozen=True)
class Case:
    """A validated case. Absent optional sections are ``None`` (their model is off)."""

    path: Path
    run: Section
    mesh: Section
    box: Section | None
    patches: tuple  # of Section: named parts of a box's sides
    fluid: Section | None
    boundaries: dict  # name → Section (only those listed in the file)
    coupling: Section | None
    particles: Section | None
    particles_add: tuple  # of Section
    collisions: Section | None
    field_forces: Section | None
    injections: tuple  # of Section
    bodies: tuple  # of Section: immersed rigid bodies of prescribed motion
    deposition: Section | None

    @property
    def folder(self) -> Path:
        return self.path.parent

    def resolve(self, relative: str) -> Path:
        """A path from the case, relative to the case file's folder."""
        return (self.folder / relative).resolve()

    def models(self) -> list[str]:
        """The models this case switches on, in the order of a time step."""
        names = ["particles" if (self.particles or self.injections) else None,
                 "flow" if self.fluid else None,
                 f"coupling ({self.coupling.mode})" if self.fluid and self.coupling else None,
                 "collisions" if self.collisions else None,
                 "field forces" if self.field_forces else None,
                 "injection" if self.injections else None,
                 "bodies" if self.bodies else None,
                 "deposition" if self.deposition else None]
        return [n for n in names if n]


# ----------------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------------
def case_path(argument: str) -> Path:
    """``CASE`` on the command line: a folder holding case.toml, or a .toml file."""
    path = Path(argument)
    if path.is_dir():
        path = path / "case.toml"
    if not path.is_file():
        raise CaseError(f"{argument}: no case file here (expected a folder holding case.toml, or a .toml file)")
    return path.resolve()


def load_case(path: Path, overrides: list[str] = ()) -> Case:
    """Read, override (``--set KEY=VALUE``) and validate a case file."""
    try:
        # utf-8-sig: a byte-order mark, as some Windows editors write one, is not part of the TOML
        raw = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except tomllib.TOMLDecodeError as error:
        raise CaseError(f"{path.name}: not valid TOML: {error}") from None
    except (OSError, UnicodeDecodeError) as error:
        raise CaseError(f"{path.name}: cannot read: {error}") from None
    for override in overrides:
        apply_override(raw, override, path.name)
    return build_case(raw, path)


def apply_override(raw: dict, text: str, filename: str) -> None:
    """Apply one ``--set a.b.c=VALUE`` to the raw TOML dict; VALUE is a TOML value or a bare word."""
    dotted, sep, value_text = text.partition("=")
    dotted = dotted.strip()
    if not sep or not dotted:
        raise CaseError(f"--set {text}: expected KEY=VALUE, e.g. --set fluid.viscosity=0.1")
    try:
        value = tomllib.loads(f"v = {value_text}")["v"]
    except tomllib.TOMLDecodeError:
        value = value_text.strip()  # a bare word: --set coupling.mode=one-way
    parts = dotted.split(".")
    section = parts[0]
    if section not in SECTIONS:
        raise CaseError(f"--set {dotted}: unknown section [{section}]{suggest(section, SECTIONS)}")
    table_keys = {".".join(parts[:i]) for i in range(1, len(parts))}
    if table_keys & ARRAY_TABLES:
        raise CaseError(f"--set {dotted}: [[{section}]] is a list of tables; edit the case file instead")
    schema_name = "boundary.*" if section == "boundary" and len(parts) == 3 else ".".join(parts[:-1])
    keys = SCHEMA.get(schema_name)
    if keys is None or parts[-1] not in {k.name for k in keys}:
        known = [k.name for k in keys] if keys else []
        raise CaseError(f"--set {dotted}: no such key{suggest(parts[-1], known)}")
    # a bad value is the command line's, not the case file's: say so
    key = next(k for k in keys if k.name == parts[-1])
    check_value(value, key, ".".join(parts[:-1]), filename, where=f"--set {dotted}={value_text.strip()}")
    node = raw
    for part in parts[:-1]:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise CaseError(f"--set {dotted}: {part} is not a table in {filename}")
    node[parts[-1]] = value


def suggest(word: str, candidates) -> str:
    """' (did you mean "x"?)' for the nearest candidate, or a list of the allowed ones."""
    close = difflib.get_close_matches(word, list(candidates), n=1, cutoff=0.6)
    if close:
        return f' (did you mean "{close[0]}"?)'
    return f"; allowed: {', '.join(candidates)}" if candidates else ""


def build_case(raw: dict, path: Path) -> Case:
    name = path.name
    for section, value in raw.items():
        if not isinstance(value, (dict, list)):
            raise CaseError(f"{name}: key \"{section}\" stands outside any [section]")
        if section not in SECTIONS:
            raise CaseError(f"{name}: unknown section [{section}]{suggest(section, SECTIONS)}")
    for section in ("run", "mesh"):
        if section not in raw:
            raise CaseError(f"{name}: missing section [{section}] (required)")

    def table(schema_name: str, label: str, required: bool = False) -> Section | None:
        data = raw
        for part in label.split("."):
            data = data.get(part) if isinstance(data, dict) else None
        if data is None:
            if required:
                raise CaseError(f"{name}: missing section [{label}] (required)")
            return None
        if not isinstance(data, dict):
            raise CaseError(f"{name}: [{label}] must be a table")
        return Section(check_table(data, SCHEMA[schema_name], label, name))

    mesh_raw = raw["mesh"]
    if not isinstance(mesh_raw, dict):
        raise CaseError(f"{name}: [mesh] must be a table")
    mesh = Section(check_table({k: v for k, v in mesh_raw.items() if k not in ("box", "patch")}, SCHEMA["mesh"],
                               "mesh", name, extra=("box", "patch")))
    box = table("mesh.box", "mesh.box")
    if (box is None) == (mesh.file is None):
        raise CaseError(f"{name}: [mesh] needs exactly one of box = {{...}} or file = \"...\"")
    patches = array_of_tables(mesh_raw.get("patch", []), "mesh.patch", name)
    if patches and box is None:
        raise CaseError(f"{name}: [[mesh.patch]] names parts of a box's sides; a mesh file names its own boundaries")

    boundaries_raw = raw.get("boundary", {})
    if not isinstance(boundaries_raw, dict):
        raise CaseError(f"{name}: [boundary] must hold tables [boundary.<name>]")
    boundaries = {}
    for bname, data in boundaries_raw.items():
        if not isinstance(data, dict):
            raise CaseError(f"{name}: [boundary.{bname}] must be a table")
        boundaries[bname] = Section(check_table(data, SCHEMA["boundary.*"], f"boundary.{bname}", name))

    particles_raw = raw.get("particles")
    particles = particles_add = None
    if particles_raw is not None:
        if not isinstance(particles_raw, dict):
            raise CaseError(f"{name}: [particles] must be a table")
        particles = Section(check_table({k: v for k, v in particles_raw.items() if k != "add"},
                                        SCHEMA["particles"], "particles", name, extra=("add",)))
        particles_add = array_of_tables(particles_raw.get("add", []), "particles.add", name)
    injections = array_of_tables(raw.get("injection", []), "injection", name)
    bodies = array_of_tables(raw.get("body", []), "body", name)

    case = Case(
        path=path,
        run=table("run", "run", required=True),
        mesh=mesh,
        box=box,
        patches=patches,
        fluid=table("fluid", "fluid"),
        boundaries=boundaries,
        # a flow with particles is coupled by default
        coupling=table("coupling", "coupling") or (Section(check_table({}, SCHEMA["coupling"], "coupling", name))
                                                   if "fluid" in raw else None),
        particles=particles,
        particles_add=particles_add or (),
        collisions=table("collisions", "collisions"),
        field_forces=table("field_forces", "field_forces"),
        injections=injections,
        bodies=bodies,
        deposition=table("deposition", "deposition"),
    )
    check_consistency(case)
    return case


def array_of_tables(data, label: str, filename: str) -> tuple:
    if not isinstance(data, list) or not all(isinstance(d, dict) for d in data):
        raise CaseError(f"{filename}: [[{label}]] must be a list of tables")
    return tuple(Section(check_table(d, SCHEMA[label], f"{label}[{i}]", filename)) for i, d in enumerate(data))


def check_table(data: dict, keys: tuple[Key, ...], label: str, filename: str, extra=()) -> dict:
    """Typed values of one table; refuses unknown keys, wrong types and values out of range."""
    known = {k.name: k for k in keys}
    for key in data:
        if key not in known and key not in extra:
            raise CaseError(f"{filename}: [{label}] unknown key \"{key}\"{suggest(key, list(known) + list(extra))}")
    values = {}
    for key in keys:
        if key.name in data:
            values[key.name] = check_value(data[key.name], key, label, filename)
        elif key.default is REQUIRED:
            raise CaseError(f"{filename}: [{label}] missing key \"{key.name}\"{describe(key)}")
        else:
            values[key.name] = key.default
    return values


def describe(key: Key) -> str:
    what = {"float": "a number", "int": "an integer", "bool": "true or false", "str": "a string",
            "vec3": "three numbers [x, y, z]", "ivec3": "three integers [nx, ny, nz]",
            "strings": "a list of strings"}[key.kind]
    unit = f" ({key.unit})" if key.unit else ""
    return f" ({what}{unit})"


def check_value(value, key: Key, label: str, filename: str, where: str = ""):
    """The typed value of one key, or CaseError naming ``where`` (default: the file, table and key)."""
    where = where or f"{filename}: [{label}] {key.name} = {format_value(value)}"
    kind = key.kind
    ok = True
    if kind == "float":
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
        # inf only where it is the default, i.e. means "never" ([[injection]] stop)
        ok = ok and (math.isfinite(value) or (value == math.inf and key.default == math.inf))
    elif kind == "int":
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif kind == "bool":
        ok = isinstance(value, bool)
    elif kind == "str":
        ok = isinstance(value, str)
    elif kind in ("vec3", "ivec3"):
        scalar = int if kind == "ivec3" else (int, float)
        ok = (isinstance(value, list) and len(value) == 3
              and all(isinstance(v, scalar) and not isinstance(v, bool) for v in value))
        if ok:
            value = tuple(int(v) if kind == "ivec3" else float(v) for v in value)
            ok = all(math.isfinite(v) for v in value)
    elif kind == "strings":
        ok = isinstance(value, list) and all(isinstance(v, str) for v in value)
        value = tuple(value) if ok else value
    if not ok:
        what = describe(key).strip()[1:-1]
        if isinstance(value, float) and math.isinf(value):
            what = what.replace("a number", "a finite number")
        raise CaseError(f"{where}: must be {what}")
    if key.choices and value not in key.choices:
        raise CaseError(f"{where}: must be one of {', '.join(map(repr, key.choices))}"
                        f"{suggest(value, key.choices) if isinstance(value, str) else ''}")
    numbers = value if isinstance(value, tuple) else (value,)
    unit = f" ({key.unit})" if key.unit else ""
    if key.check == ">0" and not all(v > 0 for v in numbers):
        raise CaseError(f"{where}: must be > 0{unit}")
    if key.check == ">=0" and not all(v >= 0 for v in numbers):
        raise CaseError(f"{where}: must be >= 0{unit}")
    if key.check == "0..1" and not all(0 <= v <= 1 for v in numbers):
        raise CaseError(f"{where}: must be between 0 and 1")
    if key.check == "(0,1)" and not all(0 < v < 1 for v in numbers):
        raise CaseError(f"{where}: must be > 0 and < 1")
    return value


def format_value(value) -> str:
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(format_value(v) for v in value) + "]"
    return repr(value)


def check_consistency(case: Case) -> None:
    """Checks that involve more than one key."""
    name = case.path.name
    run = case.run
    if run.output_every is None:
        object.__setattr__(case.run, "values", {**run.values, "output_every": run.end_time / 20})
    # the loop adds dt to the time: far below the resolution of a double at end_time, time stalls
    for key in ("dt", "output_every", "checkpoint_every"):
        every = getattr(run, key)
        if every is not None and not run.end_time / every <= MAX_STEPS:
            raise CaseError(f"{name}: [run] {key} = {every:g} s is too small for end_time = {run.end_time:g} s: "
                            f"{run.end_time / every:.3g} intervals, more than the {MAX_STEPS:.2g} that "
                            f"double-precision time can count; raise {key} or lower end_time")
    if case.box is not None:
        lower, upper = case.box.lower, case.box.upper
        if not all(u > l for l, u in zip(lower, upper)):
            raise CaseError(f"{name}: [mesh.box] upper = {format_value(upper)} must exceed lower = "
                            f"{format_value(lower)} in every direction")
    for bname, b in case.boundaries.items():
        if b.motion == "rigid" and case.fluid is not None and b.type == "wall" and any(b.velocity + b.angular_velocity):
            raise CaseError(f"{name}: [boundary.{bname}] motion = \"rigid\" moves the wall itself, which the "
                            "fixed flow mesh cannot follow; for a paddle or a plate moving in the fluid use a [[body]], "
                            "or motion = \"surface\" for a wall whose surface slides along itself")
    for bname, b in case.boundaries.items():
        if b.type == "wall" and b.particles == "pass":
            raise CaseError(f"{name}: [boundary.{bname}] particles = \"pass\": particles cannot pass a wall; make the "
                            "boundary an outlet (or an inlet) to let them through")
    coupling = case.coupling
    if coupling is not None and coupling.drag_correction != "off" and \
            (coupling.forcing != "penalty" or coupling.mode != "two-way"):
        raise CaseError(f"{name}: [coupling] drag_correction = \"{coupling.drag_correction}\" acts through the "
                        f"penalty's rates: it needs forcing = \"penalty\" and mode = \"two-way\" (here forcing = "
                        f"\"{coupling.forcing}\", mode = \"{coupling.mode}\")")
    needs = {"box": ("size",), "cylinder": ("radius", "length"), "surface": ("file",)}
    for i, body in enumerate(case.bodies):
        missing = [key for key in needs[body.shape] if getattr(body, key) is None]
        if missing:
            raise CaseError(f"{name}: [[body]] #{i}: shape = \"{body.shape}\" needs "
                            + " and ".join(f"{key} = ..." for key in missing))
        if body.shape == "cylinder" and not any(body.axis):
            raise CaseError(f"{name}: [[body]] #{i}: axis = [0, 0, 0] has no direction")
    if case.bodies and case.fluid is None and case.collisions is None:
        raise CaseError(f"{name}: [[body]] acts on nothing without [fluid] (it drives the fluid) or [collisions] "
                        "(particles bounce off it); add one of them")
    for i, inj in enumerate(case.injections):
        if inj.stop < inj.start:
            raise CaseError(f"{name}: [[injection]] #{i}: stop = {inj.stop} must be >= start = {inj.start}")
        if not (min(inj.stop, run.end_time) - inj.start) / inj.interval <= MAX_STEPS:
            raise CaseError(f"{name}: [[injection]] #{i}: interval = {inj.interval:g} s is too small: more than "
                            f"{MAX_STEPS:.2g} releases before end_time; raise interval")
        if inj.kind == "random" and (inj.lower is None or inj.upper is None):
            raise CaseError(f"{name}: [[injection]] #{i}: kind = \"random\" needs lower = [...] and upper = [...]")
        if inj.kind == "random" and not all(l <= u for l, u in zip(inj.lower, inj.upper)):
            raise CaseError(f"{name}: [[injection]] #{i}: lower = {format_value(inj.lower)} must not exceed upper = "
                            f"{format_value(inj.upper)} in any direction (the box of release points)")
        if inj.kind == "cylindrical" and inj.origin is None:
            raise CaseError(f"{name}: [[injection]] #{i}: kind = \"cylindrical\" needs origin = [...]")
    if case.deposition is not None:
        for zone in case.deposition.zones:
            if zone in case.boundaries and case.boundaries[zone].type != "wall":
                raise CaseError(f"{name}: [deposition] zones: \"{zone}\" is a {case.boundaries[zone].type}, not a wall")
