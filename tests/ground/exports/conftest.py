"""One small flight shared by the export tests: a 30 x 20 x 10 m building turned 30 deg from north, a
frustum pile against nothing, the report with every export, and the survey it wrote them from."""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import pytest

from firmware_py.core.samplelog import SampleLogWriter, read_samplelog, rewritable_header
from firmware_py.core.site import Site
from firmware_py.core.storage import Storage
from ground import report
from ground.exports.formats import ExportFormat
from ground.report import ReportOptions, Survey, make_report, survey_from_samples
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from tests.sitl.conftest import frustum_mesh

SITE = Site.of(-33.8568, 151.2153, 12.0, 30.0)  # southern hemisphere, far from the zone's central meridian
STORAGE = Storage(30, 20, 10)


@dataclass(frozen=True)
class Flown:
    run: Path
    report_dir: Path
    report: dict
    survey: Survey
    header: dict


@pytest.fixture(scope="session")
def flown(tmp_path_factory) -> Flown:
    tmp = tmp_path_factory.mktemp("exports")
    pile = tmp / "cone.stl"
    frustum_mesh(6.0, 1.0, 4.0, (15.0, 10.0)).export(pile)
    cfg = FlyConfig(mission=Mission(storage=STORAGE, altitude_m=9.0, p_traj=0.2), stockpile=str(pile), site=SITE)
    fly(cfg, tmp / "run")
    opts = ReportOptions(plots=False, exports=tuple(ExportFormat))
    surveys = []

    def surveyed(*args, **kwargs):
        """The report's own survey, kept as a copy taken before any writer saw it."""
        survey = survey_from_samples(*args, **kwargs)
        surveys.append(copy.deepcopy(survey))
        return survey
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(report, "survey_from_samples", surveyed)
        rep = make_report(tmp / "run", tmp / "rep", opts)
    log = read_samplelog(tmp / "run" / "samples.pslog")
    (survey,) = surveys  # what the exports were written from (surveying the log again gave the same)
    return Flown(tmp / "run", tmp / "rep", rep, survey, log.header)


def without_site(flown: Flown, out: Path) -> Path:
    """The flight's log with the site taken out of its header."""
    log = read_samplelog(flown.run / "samples.pslog")
    header = {k: v for k, v in rewritable_header(log.header).items() if k != "site"}
    w = SampleLogWriter(out, header)
    w.append(log.samples)
    w.close()
    return out
