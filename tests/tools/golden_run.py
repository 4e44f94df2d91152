"""The golden flight stored as an evaluation run, for the tests of the checks that read the stored set."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from firmware_py.core.samplelog import read_samplelog

GOLDEN = Path(__file__).resolve().parents[1] / "golden"
RUN = "golden-cone-0-none"


def store_golden_run(root: Path, **truth) -> Path:
    """Write the golden log under root/runs/RUN as `tools.evalset` stores a run (samples.npy, header.json, and
    truth.json last: a cone without noise in the held-out split, with the given truth fields on top); the run's
    folder."""
    run = root / "runs" / RUN
    run.mkdir(parents=True)
    log = read_samplelog(GOLDEN / "samples.pslog")
    np.save(run / "samples.npy", log.samples)
    (run / "header.json").write_text(json.dumps(log.header))
    (run / "truth.json").write_text(json.dumps({"run_id": RUN, "family": "cone", "noise": "none",
                                                "split": "heldout", **truth}))
    return run


def golden_true_volume_m3() -> float:
    """The golden flight's true volume (its truth.json)."""
    return json.loads((GOLDEN / "truth.json").read_text())["true_volume_m3"]
