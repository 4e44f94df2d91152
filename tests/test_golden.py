"""Golden files: a checked-in sample log of the current format and the report figures it must give.

`tests/golden/samples.pslog` is a cut-down real run (pile 1, P_traj 20 %, the payload firmware in the
loop on the JSBSim plant, every 20th sample: 3,204 samples, 190 KB), `truth.json` its true volume and
`report_figures.json` the `report.json` values the ground report gave on it. A change to the log
format, the reader or the report therefore shows as a failing test here and as a diff of these files.

When the change is intended, regenerate and commit the files with it (the diff is the review):

    python -m tools.make_golden            # rewrites tests/golden/ (about 10 s, deterministic)
    python -m tools.make_golden --check    # exit 1 when regenerating would change a file
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from firmware_py.app import PayloadConfig
from firmware_py.core.frames import StorageFrame
from firmware_py.core.header import build_log_header
from firmware_py.core.rundir import SAMPLES_FILE, TRUTH_FILE
from firmware_py.core.samplelog import FORMAT_NAME, FORMAT_VERSION, SAMPLE_DTYPE, SampleLogWriter, read_samplelog
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import Waveform
from ground.report import ReportOptions, make_report
from tools.make_golden import REL_TOL, figure_differences

GOLDEN = Path(__file__).resolve().parent / "golden"
FIGURES = json.loads((GOLDEN / "report_figures.json").read_text())
REL = 1e-6  # floats: tight, but not bit-exact across BLAS builds and CPUs


def golden_log():
    return read_samplelog(GOLDEN / SAMPLES_FILE)


def standard_header(h: dict) -> dict:
    """The header `build_log_header` writes today for the golden header's values, without extra keys."""
    servo = h["servo"]
    wf = Waveform(servo["shape_c"], servo["frequency_hz"], servo["amplitude_rad"], servo["phase_rad"],
                  servo["direction"])
    return build_log_header(source=h["source"], sensor=h["sensor"], lever_arm_body_m=h["lever_arm_body_m"],
                            waveform_name=servo["waveform"], waveform=wf,
                            initial_position=servo["initial_position"], storage=Storage.from_dict(h["storage"]),
                            frame=StorageFrame.from_dict(h["storage_frame"]), mission_id=h["mission_id"],
                            mission=h["mission"], created_utc=h["created_utc"])


def assert_same_figure(key: str, got, want) -> None:
    """Exact for counts, strings and structure; floats within REL (`tools.make_golden.figure_differences`)."""
    diffs = figure_differences(key, got, want, REL)
    assert not diffs, diffs


def test_that_the_golden_log_is_of_the_current_format_version_and_reads_whole():
    log = golden_log()
    assert log.header["format"] == FORMAT_NAME and log.header["format_version"] == FORMAT_VERSION
    assert log.header["record_dtype"] == [list(field) for field in SAMPLE_DTYPE.descr]
    assert log.samples.dtype == SAMPLE_DTYPE and len(log.samples) == FIGURES["n_samples"]
    assert (log.blocks_corrupt, log.blocks_truncated, log.bytes_skipped) == (0, 0, 0)
    assert np.all(np.diff(log.samples["t_s"]) > 0)


def test_that_the_writer_reproduces_the_golden_logs_header(tmp_path):
    golden = golden_log().header
    standard = standard_header(golden)
    extra = {k: v for k, v in golden.items() if k not in standard and k not in ("format", "format_version",
                                                                              "record_dtype")}
    path = tmp_path / "x.pslog"
    with SampleLogWriter(path, {**standard, **extra}, fsync=False):
        pass
    written = read_samplelog(path).header
    assert list(written) == list(golden)  # the same keys in the same order (JSON keeps it)
    assert written == golden


def test_that_the_payload_program_writes_the_golden_logs_standard_header_keys():
    standard = list(standard_header(golden_log().header))
    payload = list(PayloadConfig(storage=Storage()).log_header())
    assert payload[:len(standard)] == standard


def test_that_the_ground_report_on_the_golden_log_gives_the_golden_figures(tmp_path):
    make_report(GOLDEN, tmp_path, ReportOptions(plots=False))
    report = json.loads((tmp_path / "report.json").read_text())
    for key, want in FIGURES.items():
        assert_same_figure(key, report[key], want)
    truth = json.loads((GOLDEN / TRUTH_FILE).read_text())
    assert report["true_volume_m3"] == truth["true_volume_m3"]


def test_that_the_golden_check_passes_the_last_digits_of_a_float_and_catches_a_changed_figure():
    """`make_golden --check` re-flies the log on the machine it runs on: a float sum's last digits move between
    machines (the pile's volume ...369 on one, ...367 on another), which is no change of the format or the report."""
    def same(made: dict) -> bool:
        return not figure_differences("truth", made, kept, REL_TOL)
    kept = {"true_volume_m3": 7206.878773739369, "warnings": ["a"], "n": 3, "ok": True}
    assert same({**kept, "true_volume_m3": 7206.878773739367})
    assert not same({**kept, "true_volume_m3": 7206.88})
    assert not same({**kept, "warnings": ["b"]}) and not same({**kept, "n": 4})
    assert not same({**kept, "ok": 1}) and not same({k: kept[k] for k in ("n", "ok")})
