"""The case file: typed values, defaults, --set overrides, one clear error per bad input."""
import pytest

from pmpm.case import apply_override, case_path, load_case
from pmpm.errors import CaseError

BASE = """
[run]
end_time = 1.0
dt = 1e-3
[mesh]
box = { lower = [0, 0, 0], upper = [0.1, 0.1, 0.16], cells = [4, 4, 6] }
[fluid]
density = 1000.0
viscosity = 1e-3
[boundary.xmin]
type = "inlet"
velocity = [0.5, 0, 0]
[[particles.add]]
position = [0.05, 0.05, 0.12]
radius = 0.0075
density = 1120.0
"""


def write_case(tmp_path, text=BASE):
    path = tmp_path / "case.toml"
    path.write_text(text)
    return path


def test_values_and_defaults(tmp_path):
    case = load_case(write_case(tmp_path))
    assert case.fluid.viscosity == 1e-3
    assert case.run.gravity == (0.0, 0.0, -9.81)
    assert case.run.output_every == pytest.approx(0.05)  # default: 20 outputs
    assert case.boundaries["xmin"].velocity == (0.5, 0.0, 0.0)
    assert case.particles_add[0].motion == "free"
    assert case.collisions is None and case.injections == ()


def test_case_path_accepts_folder_or_file(tmp_path):
    path = write_case(tmp_path)
    assert case_path(str(tmp_path)) == path.resolve() == case_path(str(path))
    with pytest.raises(CaseError, match="no case file"):
        case_path(str(tmp_path / "nothing"))


def test_set_overrides(tmp_path):
    case = load_case(write_case(tmp_path), ["fluid.viscosity=0.1", "mesh.box.cells=[2,3,4]",
                                            "coupling.mode=one-way", 'boundary.xmax.type="outlet"'])
    assert case.fluid.viscosity == 0.1
    assert case.box.cells == (2, 3, 4)
    assert case.coupling.mode == "one-way"
    assert case.boundaries["xmax"].type == "outlet"


@pytest.mark.parametrize("override, message", [
    ("fluid.viscosty=1", 'no such key (did you mean "viscosity"?)'),
    ("flud.density=1", 'unknown section [flud] (did you mean "fluid"?)'),
    ("particles.add.radius=1", "list of tables"),
    ("novalue", "expected KEY=VALUE"),
    ("collisions.dense_sweeps=0", "dense_sweeps=0: must be > 0"),
    ("collisions.dense_sweeps=2.5", "dense_sweeps=2.5: must be an integer"),
])
def test_set_refuses_unknown_keys(tmp_path, override, message):
    with pytest.raises(CaseError) as error:
        load_case(write_case(tmp_path), [override])
    assert message in str(error.value)


@pytest.mark.parametrize("change, message", [
    (("viscosity = 1e-3", "viscosty = 1e-3"), '[fluid] unknown key "viscosty" (did you mean "viscosity"?)'),
    (("[fluid]", "[fluidd]"), 'unknown section [fluidd] (did you mean "fluid"?)'),
    (("viscosity = 1e-3", "viscosity = -1e-3"), "[fluid] viscosity = -0.001: must be > 0 (Pa s)"),
    (("viscosity = 1e-3", 'viscosity = "thick"'), '[fluid] viscosity = "thick": must be a number (Pa s)'),
    (("radius = 0.0075", "radius = 0.0"), "[particles.add[0]] radius = 0.0: must be > 0 (m)"),
    (("density = 1120.0", "density = -5.0"), "[particles.add[0]] density = -5.0: must be > 0"),
    (("dt = 1e-3", "dt = 0.0"), "[run] dt = 0.0: must be > 0 (s)"),
    (("end_time = 1.0", "end_time = -1.0"), "[run] end_time = -1.0: must be > 0 (s)"),
    (('type = "inlet"', 'type = "inlte"'), 'must be one of \'wall\', \'inlet\', \'outlet\', \'symmetry\' (did you mean "inlet"?)'),
    (("cells = [4, 4, 6]", "cells = [4, 4]"), "cells = [4, 4]: must be three integers [nx, ny, nz]"),
    (("[run]\nend_time = 1.0\ndt = 1e-3\n", ""), "missing section [run]"),
    (("[run]\n", ""), 'key "end_time" stands outside any [section]'),
    (("dt = 1e-3", "dt = "), "not valid TOML"),
])
def test_bad_input_one_line(tmp_path, change, message):
    with pytest.raises(CaseError) as error:
        load_case(write_case(tmp_path, BASE.replace(*change, 1)))
    text = str(error.value)
    assert message in text
    assert "\n" not in text and text.startswith(("case.toml", "--set"))


def test_override_applies_to_raw_table():
    raw = {"run": {"dt": 1.0}}
    apply_override(raw, "run.dt=0.5", "case.toml")
    assert raw["run"]["dt"] == 0.5


@pytest.mark.parametrize("change, message", [
    (("end_time = 1.0", "end_time = inf"), "[run] end_time = inf: must be a finite number (s)"),
    (("viscosity = 1e-3", "viscosity = inf"), "[fluid] viscosity = inf: must be a finite number (Pa s)"),
    (("dt = 1e-3", "dt = 1e-300"), "[run] dt = 1e-300 s is too small for end_time = 1 s"),
    (("[[particles.add]]", '[[injection]]\nkind = "random"\nlower = [0, 0, 0.1]\nupper = [0.1, 0.1, 0.05]\n'
      'interval = 0.1\nradius = 0.001\ndensity = 1.0\n[[particles.add]]'),
     "[[injection]] #0: lower = [0.0, 0.0, 0.1] must not exceed upper = [0.1, 0.1, 0.05] in any direction"),
    (("[[particles.add]]", '[coupling]\nforcing = "patch"\ndrag_correction = "di_felice"\n[[particles.add]]'),
     '[coupling] drag_correction = "di_felice" acts through the penalty\'s rates: it needs forcing = "penalty" and '
     'mode = "two-way" (here forcing = "patch", mode = "two-way")'),
    (("[[particles.add]]", '[coupling]\ndrag_correction = "ergun"\n[[particles.add]]'),
     '[coupling] drag_correction = "ergun"'),
    (("[[particles.add]]", '[coupling]\ncorrection_filter = -0.01\n[[particles.add]]'),
     "[coupling] correction_filter = -0.01"),
])
def test_values_that_cannot_run_are_refused(tmp_path, change, message):
    with pytest.raises(CaseError) as error:
        load_case(write_case(tmp_path, BASE.replace(*change, 1)))
    assert message in str(error.value) and "\n" not in str(error.value)


def test_injection_may_stop_never(tmp_path):
    text = BASE + '[[injection]]\nposition = [0.05, 0.05, 0.1]\ninterval = 0.1\nradius = 0.001\ndensity = 1.0\nstop = inf\n'
    assert load_case(write_case(tmp_path, text)).injections[0].stop == float("inf")


@pytest.mark.parametrize("override, message", [
    ("run.dt=abc", "--set run.dt=abc: must be a number (s)"),
    ("run.end_time=inf", "--set run.end_time=inf: must be a finite number (s)"),
    ("fluid.viscosity=-1", "--set fluid.viscosity=-1: must be > 0 (Pa s)"),
    ("mesh.box.cells=[4,4]", "--set mesh.box.cells=[4,4]: must be three integers [nx, ny, nz]"),
    ('boundary.xmax.type="outflow"', '--set boundary.xmax.type="outflow": must be one of'),
])
def test_bad_set_value_is_blamed_on_set_not_the_file(tmp_path, override, message):
    with pytest.raises(CaseError) as error:
        load_case(write_case(tmp_path), [override])
    assert str(error.value).startswith(message) and "case.toml" not in str(error.value)


def test_byte_order_mark_is_accepted(tmp_path):
    path = tmp_path / "case.toml"
    path.write_bytes(b"\xef\xbb\xbf" + BASE.encode())
    assert load_case(path).fluid.viscosity == 1e-3
