"""Property-based: broken case files and --set values never give a traceback.

Hypothesis mutates a valid case (a value replaced by anything TOML or not, a line dropped, doubled
or added) and draws --set KEY=VALUE pairs; pmpm --check must then either accept the case (exit 0)
or refuse it with exit 2 and one line on stderr. Examples run in-process on 1 rank; a few go
through ``mpirun -n 2``. Derandomized, so the suite is repeatable and bounded in time.
"""
import io
import tempfile
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pmpm.__main__ import main
from pmpm.schema import ARRAY_TABLES, SCHEMA
from test_cli import run_pmpm

# small on purpose: any mutation of it that stays valid builds in well under a second; within the
# coupling's validated range (4 and 3.2 cells per diameter, Re ≈ 1), so it warns of nothing
BASE = """[run]
end_time = 0.02
dt = 0.005
output_every = 0.01
checkpoint_every = 0.01
gravity = [0.0, 0.0, -9.81]
[mesh]
box = { lower = [0, 0, 0], upper = [0.1, 0.1, 0.1], cells = [20, 20, 20] }
[fluid]
density = 1000.0
viscosity = 1.0
[boundary.xmin]
type = "inlet"
velocity = [0.01, 0.0, 0.0]
[boundary.xmax]
type = "outlet"
[[particles.add]]
position = [0.05, 0.05, 0.05]
radius = 0.01
density = 2000.0
[collisions]
restitution = 0.5
[[injection]]
kind = "random"
lower = [0.02, 0.02, 0.06]
upper = [0.08, 0.08, 0.08]
interval = 0.01
radius = 0.008
density = 1500.0
[deposition]
zones = ["zmin"]
"""
KEYS = sorted({key.name for keys in SCHEMA.values() for key in keys} | {"box", "file", "add"})
SECTIONS = ["[run]", "[mesh]", "[fluid]", "[boundary.zmax]", "[boundary.nowhere]", "[coupling]", "[[injection]]",
            "[[particles.add]]", "[particles]", "[collisions]", "[field_forces]", "[deposition]", "[mesh.box]",
            "[fluidd]", "[[run]]", "[]"]

numbers = st.one_of(st.integers(-3, 12), st.sampled_from([0.0, -0.0, -1.0, 1e-300, 5e-324, 1e300, 1e308, 2.0 ** 63]),
                    st.floats(-1.0, 1.0))
literals = st.one_of(
    st.sampled_from(["inf", "-inf", "nan", "0", "-1", "1e300", "1e-300", "true", '""', "[]", "{}"]),  # often
    numbers.map(repr),
    st.sampled_from(["+inf", "false", '"inlet"', '"outlet"', '"wall"',
                     '"tet"', '"hex"', '"subcell"', '"one-way"', '"random"', '"cylindrical"', '"zmin"', '"nope.msh"',
                     '"."', "[]", "{}", "[[]]", "1979-05-27", "0x10", "1_000", "'lit'", '"""x"""', "[1, 2]",
                     "[0.05, 0.05]", '["zmin", "xmax"]', "{ lower = [0, 0, 0] }", "[1, 2, 3, 4]", "= 1", ""]),
    st.lists(numbers.map(repr), min_size=0, max_size=4).map(lambda v: "[" + ", ".join(v) + "]"),
    st.text(st.characters(blacklist_categories=("Cs",)), max_size=12),
)


@st.composite
def broken_cases(draw) -> str:
    """The base case with one to three mutations of its lines."""
    lines = BASE.splitlines()
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["value", "value", "drop", "double", "add key", "add section", "garbage"]))
        at = draw(st.integers(0, len(lines) - 1))
        if kind == "value":
            at = draw(st.sampled_from([i for i, line in enumerate(lines) if "=" in line] or [at]))
            lines[at] = lines[at].split("=", 1)[0] + "= " + draw(literals)
        elif kind == "drop":
            del lines[at]
        elif kind == "double":
            lines.insert(at, lines[at])
        elif kind == "add key":
            lines.insert(at, f"{draw(st.sampled_from(KEYS))} = {draw(literals)}")
        elif kind == "add section":
            lines.insert(at, draw(st.sampled_from(SECTIONS)))
        else:
            lines.insert(at, draw(st.text(max_size=20)))
    return "\n".join(lines) + "\n"


SET_KEYS = sorted({f"{section.replace('*', 'xmin')}.{key.name}" for section, keys in SCHEMA.items()
                   if section not in ARRAY_TABLES for key in keys}
                  | {"run", "run.", ".dt", "run.dt.x", "boundary.zmax", "injection.radius", "nothing.here"})
set_values = st.tuples(st.one_of(st.sampled_from(SET_KEYS), st.text(max_size=10)),
                       st.one_of(literals, st.text(max_size=10))).map(lambda kv: f"{kv[0]}={kv[1]}")


def check_in_process(case_text: str, overrides=()) -> tuple[int, str, str]:
    """``pmpm CASE --check --set ...`` on this rank: (status, stdout, stderr)."""
    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "case.toml").write_text(case_text, encoding="utf-8", errors="surrogatepass")
        arguments = [folder, "--check", "--quiet"] + [a for o in overrides for a in ("--set", o)]
        out, err = io.StringIO(), io.StringIO()
        with redirect_stdout(out), redirect_stderr(err):
            status = main(arguments)
    return status, out.getvalue(), err.getvalue()


def assert_exit_0_or_one_line(status: int, out: str, err: str) -> None:
    assert "Traceback" not in out + err, err
    assert status in (0, 2), err
    if status == 2:
        errors = [line for line in err.splitlines() if line.strip()]
        assert len(errors) == 1 and errors[0].startswith("pmpm: error: "), err


SETTINGS = dict(deadline=None, database=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@settings(max_examples=150, **SETTINGS)
@given(broken_cases())
def test_broken_case_file_exits_0_or_2_with_one_line(case_text):
    assert_exit_0_or_one_line(*check_in_process(case_text))


@settings(max_examples=150, **SETTINGS)
@given(st.lists(set_values, min_size=1, max_size=3))
def test_set_values_exit_0_or_2_with_one_line(overrides):
    assert_exit_0_or_one_line(*check_in_process(BASE, overrides))


@settings(max_examples=4, **SETTINGS)
@given(broken_cases(), st.lists(set_values, max_size=1))
def test_broken_input_on_two_ranks(case_text, overrides):
    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "case.toml").write_text(case_text, encoding="utf-8", errors="surrogatepass")
        result = run_pmpm([folder, "--check", "--quiet"] + [a for o in overrides for a in ("--set", o)], timeout=120)
    assert_exit_0_or_one_line(result.returncode, result.stdout, result.stderr)


def test_the_base_case_is_valid():
    """The mutations start from a case that runs: what they break, they broke."""
    status, out, err = check_in_process(BASE)
    assert status == 0 and not err.strip(), err
