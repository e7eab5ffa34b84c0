"""Spec loading: the paper's spec, units, defaults, and one fixture per bad input."""

from pathlib import Path

import pytest

from fabkit.errors import SpecError
from fabkit.spec import load_spec

from conftest import PAPER, SPECS, mutated, write_spec

BAD = sorted((Path(__file__).parent / "fixtures" / "bad").glob("*.yaml"))


def expected(path: Path) -> str:
    first = path.read_bytes().split(b"\n", 1)[0].decode("utf-8", "replace")
    return first.split("expect:", 1)[1].strip() if "expect:" in first else "not a text file"


def test_paper_spec_loads_with_units():
    spec = load_spec(PAPER)
    assert spec.name == "surface" and spec.units == "cm" and spec.scale == 10.0
    assert spec.surface.params["eta"] == 3.27
    assert spec.surface.x == (-44.0, 6.0)
    assert spec.tool.diameter == 6.35 and spec.ball.inertia == pytest.approx(0.4)
    assert spec.machining.pattern == "zigzag"          # a documented default
    assert spec.ramp.heights == (0.2, 4.5)


def test_all_example_specs_load():
    for path in SPECS.glob("*.yaml"):
        load_spec(path)


def test_length_strings_are_converted(tmp_path):
    spec = load_spec(write_spec(tmp_path, mutated({"tool.diameter": "1/8 in", "simulation.start": "-300 mm",
                                                   "ball.diameter": "1 in"})))
    assert spec.tool.diameter == pytest.approx(3.175, rel=1e-15)
    assert spec.simulation.start == pytest.approx(-30.0)          # design unit cm
    assert spec.ball.diameter == pytest.approx(2.54)


def test_missing_sections_are_allowed_until_needed(tmp_path):
    spec = load_spec(write_spec(tmp_path, mutated({}, drop=("tool", "machining", "stock"))))
    assert not spec.has("tool")
    with pytest.raises(SpecError, match="missing section") as info:
        spec.require("tool", command="gcode")
    assert info.value.key == "tool"


@pytest.mark.parametrize("path", BAD, ids=[p.stem for p in BAD])
def test_bad_input_fixture(path):
    with pytest.raises(SpecError) as info:
        load_spec(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(str(path))
    assert expected(path) in message


def test_did_you_mean_for_typos(tmp_path):
    with pytest.raises(SpecError, match=r"tool\.diamter: unknown key \(did you mean 'diameter'\?\)"):
        load_spec(write_spec(tmp_path, mutated({"tool.diamter": 3})))


def test_with_overrides_revalidates():
    spec = load_spec(PAPER)
    other = spec.with_overrides({"surface.params.eps": 0.1})
    assert other.surface.params["eps"] == 0.1 and spec.surface.params["eps"] == 0.25
    with pytest.raises(SpecError):
        spec.with_overrides({"tool.diameter": -1})
