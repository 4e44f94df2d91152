"""What tests compare two reports' volumes by."""

from __future__ import annotations


def ve(report: dict) -> float:
    """Signed Ve (%): eq. (8) with its sign, so that two reports compare by their volumes (report.json's
    `volume_error_pct` is the paper's unsigned Ve, which counts -0.2 % and +0.2 % as the same volume)."""
    return 100.0 * (report["volume_m3"] - report["true_volume_m3"]) / report["true_volume_m3"]
