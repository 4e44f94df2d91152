"""--export: its names, its one-line errors, what the report lists and writes, and what it leaves alone."""

import json
import sys

import pytest

from firmware_py.core.cli import ExitCode, UserError
from ground.cli import main
from ground.exports.formats import EXPORT_FILES, ExportFormat, need, parse_formats
from ground.report import REPORT_FILES, ReportOptions, make_report
from tests.ground.exports.conftest import without_site


def test_that_a_comma_list_names_formats_in_order_without_duplicates():
    assert parse_formats("tif,las") == (ExportFormat.TIF, ExportFormat.LAS)
    assert parse_formats(" LAS , las,contours") == (ExportFormat.LAS, ExportFormat.CONTOURS)
    assert parse_formats("all") == tuple(ExportFormat)
    assert parse_formats("las,all") == tuple(ExportFormat)
    assert parse_formats(None) == () and parse_formats("  ") == ()


@pytest.mark.parametrize("text, words", [("las,bogus", "'bogus'"), ("las,,tif", "empty name"), ("laz", "'laz'")])
def test_that_an_unknown_format_is_one_line_naming_it_and_the_known_ones(text, words):
    with pytest.raises(UserError) as exc:
        parse_formats(text)
    msg = str(exc.value)
    assert words in msg and "\n" not in msg and "las, tif, mesh, contours" in msg


def test_that_a_missing_library_names_the_extra_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "laspy", None)  # import laspy now raises ImportError
    with pytest.raises(UserError, match=r"needs the Python package 'laspy'.*pip install 'pilescan\[ground\]'"):
        need("laspy", ExportFormat.LAS)


def test_that_a_missing_library_is_refused_before_the_report_is_computed_or_written(flown, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "rasterio", None)
    with pytest.raises(UserError, match="rasterio"):
        make_report(flown.run, tmp_path / "rep", ReportOptions(plots=False, exports=(ExportFormat.TIF,)))
    assert not (tmp_path / "rep" / "report.json").exists()


def test_that_the_report_lists_every_export_it_wrote_and_they_are_there(flown):
    assert flown.report["exports"] == ["cloud.las", "cloud_utm.las", "surface.tif", "surface.ply",
                                       "contours.geojson", "contours_wgs84.geojson"]
    on_disk = json.loads((flown.report_dir / "report.json").read_text())
    assert on_disk["exports"] == flown.report["exports"]
    for name in flown.report["exports"]:
        assert (flown.report_dir / name).stat().st_size > 0
    assert set(EXPORT_FILES) <= set(REPORT_FILES)  # --force clears them, staging accepts them


def test_that_without_a_site_only_the_storage_frame_files_are_written(flown, tmp_path):
    log = without_site(flown, tmp_path / "nosite.pslog")
    rep = make_report(log, tmp_path / "rep", ReportOptions(plots=False, exports=tuple(ExportFormat)))
    assert rep["exports"] == ["cloud.las", "surface.tif", "surface.ply", "contours.geojson"]
    assert rep["site"] is None


def test_that_no_export_is_the_default_and_writes_nothing_more(flown, tmp_path):
    rep = make_report(flown.run, tmp_path / "rep", ReportOptions(plots=False))
    assert rep["exports"] == []
    assert not any((tmp_path / "rep" / name).exists() for name in EXPORT_FILES)


def test_that_the_cli_writes_the_exports_and_prints_them(flown, tmp_path, capsys):
    out = tmp_path / "rep"
    assert main(["report", str(flown.run), "--out", str(out), "--no-plots", "--export", "las,contours"]) == 0
    printed = capsys.readouterr().out
    rows = {line.split("  ")[0]: line.split("  ", 1)[1].strip() for line in printed.splitlines() if "  " in line}
    assert rows["exports"] == "cloud.las, cloud_utm.las, contours.geojson, contours_wgs84.geojson"
    assert (out / "cloud.las").is_file() and not (out / "surface.tif").exists()
    # --force without exports takes the old exports away with the old report
    assert main(["report", str(flown.run), "--out", str(out), "--no-plots", "--force"]) == 0
    assert not (out / "cloud.las").exists() and (out / "report.json").is_file()


def test_that_the_cli_refuses_an_unknown_format_in_one_line(flown, tmp_path, capsys):
    code = main(["report", str(flown.run), "--out", str(tmp_path / "rep"), "--export", "las,dxf"])
    err = capsys.readouterr().err
    assert code == ExitCode.USAGE, err
    assert err.count("\n") == 1 and "'dxf'" in err and "Traceback" not in err
    assert not (tmp_path / "rep").exists()
