"""Where the building stands, checked: the log header's site record, and the log's building against the [site] of
the --config file given to the report (`pilescan-ground report --config`). Neither is needed for the volume; both are
shown, and a disagreement is a warning (a wrong file somewhere)."""

from __future__ import annotations

import math

from firmware_py.core.config_file import SiteSection
from firmware_py.core.site import Site


def header_site(header: dict) -> tuple[dict | None, str | None]:
    """The header's "site" record, checked (None when the log has none), and a warning when it is malformed:
    where the building stands is shown in the report, never needed for the volume."""
    raw = header.get("site")
    if raw is None:
        return None, None
    try:
        return Site.from_dict(raw).to_dict(), None
    except ValueError as exc:
        return None, f"log header site is malformed ({exc}): not shown"


SITE_TOLERANCE_M = 0.01
"""A building dimension or corner position two records (the configuration and the log, two flights' logs, a survey
and its base) disagree on by more than this (1 cm: what a tape or a survey gives, and what the files write) is a
mismatch."""
HEADING_TOLERANCE_DEG = 0.01
"""The same for the building's heading (0.01 deg: 3.5 mm at 20 m)."""


def site_mismatches(header: dict, site: SiteSection | None, storage_given: bool = False) -> list[str]:
    """Where the log's building differs from the [site] of the --config file given to the report: one
    warning each (the report uses the log's, which is what flew, or --storage's when storage_given; a mismatch means
    a wrong file somewhere)."""
    if site is None:
        return []
    out = []
    dims = site.dimensions()
    logged = header.get("storage") or {}
    if dims is not None and isinstance(logged, dict):
        have = [logged.get(k) for k in ("length_m", "width_m", "height_m")]
        if all(isinstance(v, int | float) and not isinstance(v, bool) for v in have) and \
                max(abs(a - b) for a, b in zip(have, dims, strict=True)) > SITE_TOLERANCE_M:
            out.append(f"the log's building is {' x '.join(f'{v:g}' for v in have)} m but the --config file's [site] "
                       f"says {' x '.join(f'{v:g}' for v in dims)} m: the report uses "
                       f"{'--storage' if storage_given else 'the log'}'s (was the payload flown with another "
                       "configuration?)")
    frame = header.get("storage_frame") or {}
    heading = frame.get("heading_rad") if isinstance(frame, dict) else None
    if site.heading_deg is not None and isinstance(heading, int | float) and not isinstance(heading, bool):
        diff = (math.degrees(heading) - site.heading_deg + 180.0) % 360.0 - 180.0
        if abs(diff) > HEADING_TOLERANCE_DEG:
            out.append(f"the log's building heading is {math.degrees(heading):g} deg but the --config file's [site] "
                       f"says {site.heading_deg:g} deg: the report uses the log's")
    logged_site = ((header.get("config") or {}).get("site") or {}) if isinstance(header.get("config"), dict) else {}
    origin = logged_site.get("origin") if isinstance(logged_site, dict) else None
    if site.origin is not None and isinstance(origin, list) and len(origin) == 3 \
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in origin):
        north = math.radians(origin[0] - site.origin[0]) * 6_371_000.0
        east = math.radians(origin[1] - site.origin[1]) * 6_371_000.0 * math.cos(math.radians(site.origin[0]))
        off = math.hypot(north, east, origin[2] - site.origin[2])
        if off > SITE_TOLERANCE_M:
            out.append(f"the log's building corner is {off:.2f} m from the --config file's [site] origin: the report "
                       "uses the log's")
    return out
