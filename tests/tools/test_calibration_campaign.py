"""The calibration campaign's parts: its faults are valid SITL faults, its table marks what was applied."""

import json
import math

import numpy as np

from firmware_py.core.sensor_noise import SensorNoiseModel
from ground.self_calibration import PLANE_SETS
from sitl.faults.injector import FaultSpec
from tools.calibration_campaign import FAULTS, Case, plane_set_table, table


def test_that_every_campaign_fault_is_a_valid_sitl_fault():
    for values in FAULTS.values():
        assert set(FaultSpec(**values).active) == set(values)


def test_that_the_table_bolds_applied_estimates_and_compares_with_the_fault_free_flight():
    cal = {"servo_offset_deg": {"estimate": 3.001, "std_error": 0.002, "applied": True},
           "servo_scale": {"estimate": 0.0001, "std_error": None, "applied": False}}
    rows = [{"case": Case("1", "fault-free"), "ve_off": 0.12, "ve_on": 0.12, "cal": {}, "applied": []},
            {"case": Case("1", "servo offset 3 deg"), "ve_off": 0.20, "ve_on": 0.10, "cal": cal,
             "applied": ["servo_offset_deg"], "ve_true_mount": 0.11}]
    text = table(rows)
    # the faulted flight with its true mount given beside it; the fault-free one has none to give
    assert "| 1 | none | servo offset 3 deg | 0.20 | 0.10 | -0.02 | 0.11 | **+3.001 ± 0.002** | +0.010 |" in text
    assert "| 1 | none | fault-free | 0.12 | 0.12 | +0.00 | - |" in text
    hidden = {**cal, "reason": "the building's floor and walls were seen too little"}
    rows[1] = {**rows[1], "cal": hidden}
    assert "| - | - | - | - | the building's floor and walls were seen too little |" in table(rows)


def test_that_a_parameter_held_for_lack_of_observability_says_so_not_zero():
    cal = {"servo_offset_deg": {"estimate": 3.0, "std_error": 0.01, "applied": True, "observable": True},
           "sweep_yaw_deg": {"estimate": 0.0, "std_error": None, "applied": False, "observable": False},
           "points_per_plane": {"floor": 31, "x0": 10, "xL": 10, "y0": 5, "yW": 5}}
    rows = [{"case": Case("2", "fault-free"), "ve_off": 1.0, "ve_on": 1.0, "cal": cal, "applied": []}]
    text = table(rows)
    assert "| held (not observable) | 31 / 30 |" in text


def test_that_the_plane_set_table_names_a_parameter_a_set_does_not_see():
    sets = {name: (0 if name == "floor" else 100, np.array([1e-4, 1e-4, math.inf if name == "floor" else 2e-4, 3e-4]))
            for name in PLANE_SETS}
    text = plane_set_table([{"case": Case("2", "all three"), "plane_sets": sets}])
    assert "| 2 | none | floor | 0 | 0.0057 | 0.0100 | not seen | 0.0172 |" in text
    assert text.count("\n") == len(PLANE_SETS) + 1


def test_that_every_case_has_its_own_run_folder():
    cases = [Case(p, f, phase=k, seed=s, noise=m, payload=pl) for p in "12" for f in FAULTS for k in (0, 1)
             for s in (0, 1) for m in SensorNoiseModel for pl in ("firmware", "batch")]
    assert len({c.name for c in cases}) == len(cases)
    assert Case("1", "fault-free").name == "pile1-fault-free-k0-s0-p20"  # noise-free runs kept before stay valid


def test_that_a_noisy_flight_is_compared_with_the_fault_free_flight_of_the_same_noise_and_a_refusal_shows():
    noisy = SensorNoiseModel.DATASHEET
    refused = {"servo_offset_deg": {"estimate": 2.1, "std_error": 0.05, "applied": False},
               "refused": "not applied: it holds the planes with points inside the building"}
    rows = [{"case": Case("2", "fault-free"), "ve_off": 1.0, "ve_on": 1.0, "cal": {}, "applied": []},
            {"case": Case("2", "fault-free", noise=noisy), "ve_off": 0.6, "ve_on": 0.6, "cal": refused, "applied": []},
            {"case": Case("2", "servo offset 3 deg", noise=noisy), "ve_off": 2.9, "ve_on": 0.8, "cal": {},
             "applied": []}]
    text = table(rows)
    assert "| 2 | datasheet | servo offset 3 deg | 2.90 | 0.80 | +0.20 | - |" in text
    assert "| not applied: it holds the planes with points inside the building |" in text


def test_that_a_batch_case_flies_its_fault_with_the_batch_payload(tmp_path):
    """--payload batch: the same mounting fault, flown by the batch sampler (that it ranges as the firmware's emulated
    devices do, and that the report finds the mount, is tests/sitl/runners/test_lockstep_payload.py's)."""
    from tools.calibration_campaign import _flown
    case = Case("1", "servo offset 3 deg", p_traj=0.3, payload="batch")
    run = _flown(case, tmp_path)
    assert run == tmp_path / case.name and case.name.endswith("-batch")
    truth = json.loads((run / "truth.json").read_text())
    assert truth["payload"] == "batch" and truth["faults"]["servo_offset_deg"] == 3.0
