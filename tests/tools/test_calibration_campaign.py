"""The calibration campaign's parts: its faults are valid SITL faults, its table marks what was applied."""

from sitl.faults.injector import FaultSpec
from tools.calibration_campaign import FAULTS, Case, table


def test_that_every_campaign_fault_is_a_valid_sitl_fault():
    for values in FAULTS.values():
        assert set(FaultSpec(**values).active) == set(values)


def test_that_the_table_bolds_applied_estimates_and_compares_with_the_fault_free_flight():
    cal = {"servo_offset_deg": {"estimate": 3.001, "std_error": 0.002, "applied": True},
           "servo_scale": {"estimate": 0.0001, "std_error": None, "applied": False}}
    rows = [{"case": Case("1", "fault-free"), "ve_off": 0.12, "ve_on": 0.12, "cal": {}, "applied": []},
            {"case": Case("1", "servo offset 3 deg"), "ve_off": 0.20, "ve_on": 0.10, "cal": cal,
             "applied": ["servo_offset_deg"]}]
    text = table(rows)
    assert "| 1 | servo offset 3 deg | 0.20 | 0.10 | -0.02 | **+3.001 ± 0.002** | +0.010 |" in text
    hidden = {**cal, "reason": "the building's floor and walls were seen too little"}
    rows[1] = {**rows[1], "cal": hidden}
    assert "| - | - | - | - | the building's floor and walls were seen too little |" in table(rows)
