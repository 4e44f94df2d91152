"""Fuzzing `load_experiments` (the reproduction's TOML config): any file gives a list of valid Experiments or
one ValueError naming the file, never TypeError, AttributeError or a TOML library exception."""

from __future__ import annotations

import json
import math
import tempfile
from dataclasses import fields
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given
from hypothesis import strategies as st

from tests.fuzz_budget import budget
from tools.experiments import Experiment, load_experiments

FUZZ = budget(150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FIELDS = [f.name for f in fields(Experiment)]


@pytest.fixture(scope="module")
def workdir():
    with tempfile.TemporaryDirectory(prefix="toml-fuzz-") as d:
        yield Path(d)


def toml_value(v) -> str:
    """A TOML literal for v (str, int, float incl. nan/inf, bool, list, dict)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string (JSON escapes are TOML escapes)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(x)}" for k, x in v.items()) + "}"


scalars = st.one_of(st.text(max_size=12), st.integers(-(2**63), 2**63 - 1), st.floats(), st.booleans(),
                    st.sampled_from(["baseline", "1d", "2d", "3d", "radar", "semi-triangular", "sinusoidal", "square",
                                     "one-step", "two-step", "jsbsim", "ideal", "", "yaw-6", "a b", "x.y_z-1"]),
                    st.sampled_from([0, 1, 5, 20, 1000, 1001, -1, 0.5, 2.0, 30.0, 360.0, 361.0, 1e-9]))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                       st.dictionaries(st.text(max_size=5), inner, max_size=3)),
                      max_leaves=6)
tables = st.lists(st.dictionaries(st.one_of(st.sampled_from(FIELDS), st.text(max_size=8)), values, max_size=6),
                  max_size=4)


def as_toml(tables: list[dict]) -> str:
    return "".join("[[experiment]]\n" + "".join(f"{json.dumps(k)} = {toml_value(v)}\n" for k, v in t.items()) + "\n"
                   for t in tables)


def check_load(path: Path) -> list[Experiment] | None:
    try:
        exps = load_experiments(path)
    except ValueError as exc:
        assert type(exc) is ValueError, repr(exc)
        assert str(path) in str(exc), repr(exc)
        return None
    assert exps and all(isinstance(e, Experiment) for e in exps)
    assert len({e.name for e in exps}) == len(exps)
    return exps


@FUZZ
@given(tables=tables)
def test_that_any_experiment_tables_load_as_valid_experiments_or_fail_with_one_value_error(workdir, tables):
    path = workdir / "tables.toml"
    path.write_text(as_toml(tables))
    exps = check_load(path)
    if exps is not None:
        assert len(exps) == len(tables)
        for e in exps:
            e.mission(20)  # every loaded experiment flies (its fields were validated)


toml_ish = st.one_of(
    st.text(max_size=200),
    st.binary(max_size=200).map(lambda b: b.decode("latin-1")),
    st.lists(st.sampled_from(["[[experiment]]", "[experiment]", "[[experiment", "name = \"a\"", "name = 1",
                              "name = [1, 2]", "sensor = \"2d\"", "noise_draws = 3", "speed_m_s = nan",
                              "yaw_rate_max_dps = 1e999", "x = {a = 1}", "experiment = 5", "[[experiment.sub]]",
                              "a.b.c = 1", "\"\" = 1", "name = \"\"\"multi\nline\"\"\"", "= 3", "[" * 50,
                              "name = \"dup\"", "\x00", "\ufeff"]), max_size=10).map("\n".join),
)


@FUZZ
@given(text=toml_ish)
def test_that_random_toml_ish_text_loads_or_fails_with_one_value_error(workdir, text):
    path = workdir / "text.toml"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    check_load(path)


@FUZZ
@given(data=st.binary(max_size=300))
def test_that_random_bytes_fail_with_one_value_error(workdir, data):
    path = workdir / "bytes.toml"
    path.write_bytes(data)
    check_load(path)


@pytest.mark.parametrize("text", [
    '[[experiment]]\nname = 5\n',
    '[[experiment]]\nname = ["a"]\n',
    '[[experiment]]\nname = "a"\nsensor = ["1d"]\n',
    '[[experiment]]\nname = "a"\nwaveform = {shape = 1}\n',
    '[[experiment]]\nname = "a"\nspeed_m_s = "fast"\n',
    '[[experiment]]\nname = "a"\nnoise_draws = true\n',
    '[[experiment]]\nname = "a"\nfigure = 17\n',
    '[[experiment]]\nname = "a"\nyaw_rate_max_dps = nan\n',
])
def test_that_wrongly_typed_fields_are_refused_naming_the_file_and_the_field(workdir, text):
    path = workdir / "typed.toml"
    path.write_text(text)
    with pytest.raises(ValueError) as excinfo:
        load_experiments(path)
    assert str(path) in str(excinfo.value) and "\n" not in str(excinfo.value)
