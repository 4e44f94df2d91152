"""Fuzzing the ground station's reading of a log header: a log whose header block is intact (valid CRC, a JSON
object) but whose fields hold anything gives a report or one UserError naming the log, never a traceback."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given
from hypothesis import strategies as st

from firmware_py.core.cli import UserError
from firmware_py.core.frames import StorageFrame
from firmware_py.core.samplelog import SampleFlags, encode_block, new_records
from firmware_py.core.storage import Storage
from ground.report import ReportOptions, make_report
from tests.fuzz_budget import budget

STORAGE = Storage(20.0, 10.0, 8.0)
BASE_HEADER = {
    "storage": STORAGE.to_dict(),
    "storage_frame": StorageFrame().to_dict(),
    "lever_arm_body_m": [0.0, 0.0, 0.1],
    "sensor": {"range_sigma_m": 0.025, "range_sigma_rel": 0.01, "resolution_m": 0.01},
    "pose": {"position_sigma_m": 0.0},
    "mission_id": "fuzz",
}


def floor_samples(n: int = 400) -> np.ndarray:
    """Straight-down readings of a floor from 5 m, over a grid of the building (NED: z = -height)."""
    r = new_records(n)
    rng = np.random.default_rng(0)
    r["t_s"] = np.arange(n) * 0.01
    r["x_m"] = rng.uniform(1.0, STORAGE.length_m - 1.0, n)
    r["y_m"] = -rng.uniform(1.0, STORAGE.width_m - 1.0, n)  # W's y is NED's -east with the default frame
    r["z_m"] = -5.0
    r["range_m"] = 5.0 - 0.1 - rng.uniform(0.0, 2.0, n)  # a lumpy pile under the beam
    r["servo_rad"] = 0.0
    r["sweep_dir"] = 1
    return r


json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(),
              st.text(max_size=10), st.sampled_from([-1.0, 0.0, 1e-9, 1e308, "60", [0, 0], [0, 0, 0], [1, 2, "3"]])),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=16), inner, max_size=4)),
    max_leaves=10)
"""JSON values as a header may hold them (NaN and Infinity too: Python's json reads them)."""

field_edits = st.dictionaries(
    st.sampled_from([*BASE_HEADER, "storage.length_m", "storage_frame.heading_rad", "storage_frame.origin_ned_m",
                     "sensor.range_sigma_m", "sensor.resolution_m", "pose.position_sigma_m"]),
    st.one_of(st.just("<delete>"), json_values), max_size=4)


def edited(edits: dict, base: dict = BASE_HEADER) -> dict:
    h = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    for path, value in edits.items():
        key, _, sub = path.partition(".")
        target, name = (h, key) if not sub else (h.get(key), sub)
        if not isinstance(target, dict):
            continue
        if value == "<delete>":
            target.pop(name, None)
        else:
            target[name] = value
    return h


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("report-fuzz")


def report_or_user_error(workdir: Path, header: dict, samples: np.ndarray | None = None) -> dict | None:
    """The report of a log of this header and samples (floor_samples by default), or None for one UserError that
    names the log; report.json strict JSON."""
    log = workdir / "fuzz.pslog"  # written by hand: the writer would refuse NaN, a reader may still meet one
    samples = floor_samples() if samples is None else samples
    log.write_bytes(encode_block(b"H", json.dumps(header).encode()) + encode_block(b"S", samples.tobytes()))
    try:
        rep = make_report(log, workdir / "report", ReportOptions(plots=False), force=True)
    except UserError as exc:
        assert str(log) in str(exc) and "\n" not in str(exc)
        return None
    assert math.isfinite(rep["volume_m3"]) and rep["n_samples"] == len(samples)
    json.loads((workdir / "report" / "report.json").read_text(), parse_constant=pytest.fail)  # strict JSON
    return rep


@budget(100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(edits=field_edits)
@example(edits={"sensor.resolution_m": 1.3407807929942597e+154})  # found by a CI run: their squares overflowed
@example(edits={"sensor.range_sigma_m": 1.3407807929942597e+154})
@example(edits={"pose.position_sigma_m": 1e200})
def test_that_any_header_content_gives_a_report_or_one_user_error(workdir, edits):
    report_or_user_error(workdir, edited(edits))


def test_that_the_unedited_header_gives_a_report(workdir):
    assert report_or_user_error(workdir, edited({})) is not None


@pytest.mark.parametrize("edits", [{"sensor": "lidar"}, {"pose": [1]}, {"sensor.range_sigma_m": [0.1]},
                                   {"sensor.resolution_m": float("nan")}, {"pose.position_sigma_m": -1.0},
                                   {"storage_frame.origin_ned_m": 5}, {"storage.length_m": "sixty"}])
def test_that_a_wrongly_typed_header_field_is_named(workdir, edits):
    with pytest.raises(UserError, match=next(iter(edits)).split(".")[0]):
        make_report_from(workdir, edited(edits))


def make_report_from(workdir: Path, header: dict) -> dict:
    log = workdir / "typed.pslog"
    log.write_bytes(encode_block(b"H", json.dumps(header).encode()) + encode_block(b"S", floor_samples().tobytes()))
    return make_report(log, workdir / "typed-report", ReportOptions(plots=False), force=True)


@pytest.mark.parametrize("record", [
    {"AHRS_EKF_TYPE": 3, "EK3_SRC1_POSXY": 0, "EK3_SRC1_VELXY": 5, "EK3_SRC1_POSZ": 2},
    {"AHRS_EKF_TYPE": 3, "EK3_SRC1_VELXY": 5, "EK3_SRC1_POSZ": 1, "EK3_RNG_USE_HGT": 1e308},
    {"EK3_SRC1_POSZ": float("nan")}, "rangefinder", [2, 3], {"AHRS_EKF_TYPE": True, "EK3_SRC1_POSZ": "2"},
    {"AHRS_EKF_TYPE": 10**400, "EK3_SRC1_POSZ": 2, "EK3_RNG_USE_HGT": [1], "x": {"y": 1}}])
def test_that_any_autopilot_record_gives_a_report_that_states_it_or_not(workdir, record):
    # With a sweep period the rangefinder's share runs on a rangefinder record: on this tiny log it measures nothing.
    rep = report_or_user_error(workdir, {**edited({}), "autopilot_params": record, "servo": {"frequency_hz": 0.4}})
    assert rep is not None and isinstance(rep["pose_source"], str)
    assert rep["rangefinder_height"] is None or not rep["rangefinder_height"]["applied"]
    json.loads((workdir / "report" / "report.json").read_text(), parse_constant=pytest.fail)  # strict JSON


ECHO_HEADER = {**BASE_HEADER,
               "sensor": {"model": "Garmin LIDAR-Lite v3", "rate_hz": 500.0, "max_range_m": 10.0, "resolution_m": 0.01,
                          "range_sigma_m": 0.025, "range_sigma_rel": 0.01, "beam_divergence_rad": 0.008},
               "sensor_noise": {"reference_reflectance": 0.7, "target_reflectance": 0.3, "dropout_ramp_rel": 0.1},
               "source": "payload"}
"""A header the echo diagnosis reads (`ground.echo_reach`): a named sensor, a stated return model, a real source; its
10 m range puts part of this building's floor beyond the sure reach of the samples without an echo."""

echo_edits = st.dictionaries(
    st.sampled_from(["sensor.model", "sensor.max_range_m", "sensor_noise", "sensor_noise.reference_reflectance",
                     "sensor_noise.target_reflectance", "sensor_noise.dropout_ramp_rel", "sensor_noise.bias_m",
                     "source", "boresight", "lever_arm_body_m"]),
    st.one_of(st.just("<delete>"), json_values), max_size=3)


def echo_samples() -> np.ndarray:
    """The floor readings swept +-1.2 rad, every fifth without an echo."""
    r = floor_samples()
    r["servo_rad"] = np.linspace(-1.2, 1.2, len(r))
    r["flags"][::5] = int(SampleFlags.NO_RETURN)
    return r


def test_that_the_echo_header_gives_an_echo_record_with_floor_out_of_reach(workdir):
    rep = report_or_user_error(workdir, ECHO_HEADER, echo_samples())
    assert rep is not None and rep["echo"]["no_echo"] == 80 and rep["echo"]["beyond_reach"] > 0


@budget(40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(edits=echo_edits)
@example(edits={"sensor_noise.target_reflectance": float("nan")})
@example(edits={"source": None, "sensor_noise": "<delete>"})
def test_that_any_sensor_or_return_model_statement_gives_a_report_or_one_user_error(workdir, edits):
    report_or_user_error(workdir, edited(edits, ECHO_HEADER), echo_samples())
