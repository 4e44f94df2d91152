"""Regenerate the key reference of docs/configuration.md from the schema (`firmware_py.core.config_file`)
and the programs' option tables, so the page cannot drift from what the programs accept.

    python tools/config_reference.py            # rewrite the marked section of docs/configuration.md
    python tools/config_reference.py --check    # exit 1 if the page is out of date
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from firmware_py import cli as payload_cli  # noqa: E402
from firmware_py.core.config_file import (  # noqa: E402
    ARRAYS,
    DIMENSIONS_KEY,
    SECTIONS,
    Kind,
    range_text,
    schema_keys,
)
from firmware_py.core.geodesy import ALT_MAX_M, ALT_MIN_M  # noqa: E402
from ground import cli as ground_cli  # noqa: E402
from sitl import cli as sitl_cli  # noqa: E402
from tools.doc_sections import markers, write_section  # noqa: E402

PAGE = ROOT / "docs" / "configuration.md"
SECTION = "config-keys"
PROGRAMS = (("pilescan-payload", payload_cli.CONFIG_OPTIONS), ("pilescan-sitl", sitl_cli.CONFIG_OPTIONS),
            ("pilescan-ground", ground_cli.CONFIG_OPTIONS))


def _uses(key: str) -> str:
    """Which program and option each key sets: "pilescan-sitl fly/serve --rangefinder"."""
    look = DIMENSIONS_KEY if key in ("site.length_m", "site.width_m", "site.height_m") else key
    out = []
    for prog, tables in PROGRAMS:
        by_option: dict[str, list[str]] = {}
        for sub, table in tables.items():
            if look in table:
                by_option.setdefault(table[look], []).append(sub or "")
        for option, subs in by_option.items():
            where = f"{prog} {'/'.join(s for s in subs if s)}".strip()
            out.append(f"{where} `{option}`")
    if key.startswith("site.") and key not in ("site.name", "site.timezone"):
        out.append("pilescan-ground report (checked against the log)")
    if key.startswith("piles."):
        out.append("pilescan-ground report (names the pile holding the point; its mass)")
    return "; ".join(out) or "-"


def _example(v) -> str:
    if isinstance(v, tuple | list):
        return "[" + ", ".join(f"{x:g}" for x in v) + "]"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    return f"{v:g}"


def _limits(m) -> str:
    if m["kind"] is Kind.CHOICE:
        return ", ".join(f"`{c.value}`" for c in m["choices"])
    if m["kind"] is Kind.VECTOR:
        names = ", ".join(m["names"])
        rng = range_text(m)
        if m["names"][:2] == ("lat_deg", "lon_deg"):
            rng = f"lat -90..90, lon -180..180, alt {ALT_MIN_M:g}..{ALT_MAX_M:g}"
        return f"[{names}]" + (f"; each {rng}" if rng and not rng.startswith("lat") else f"; {rng}" if rng else "")
    rng = range_text(m)
    if m["nonzero"]:
        rng += ", not 0"
    return rng or "-"


def render() -> str:
    lines = ["| Key | Type | Unit | Allowed | Example | Meaning | Sets |", "|---|---|---|---|---|---|---|"]
    keys = schema_keys()
    for section in SECTIONS:
        for key, f in keys:
            if key.split(".")[0] != section:
                continue
            m = f.metadata
            table, _, name = key.rpartition(".")
            heading = f"[[{table}]]" if table in ARRAYS else f"[{table}]"
            lines.append(f"| `{heading}` `{name}` | {m['kind'].value} | {m['unit'] or '-'} | {_limits(m)} | "
                         f"`{_example(m['example'])}` | {m['doc']} | {_uses(key)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--check", action="store_true", help="exit 1 if docs/configuration.md is out of date")
    args = ap.parse_args(argv)
    if args.check:
        start, end = markers(SECTION)
        text = PAGE.read_text(encoding="utf-8")
        a, b = text.find(start), text.find(end)
        current = text[a + len(start):b].strip("\n") if a >= 0 and b > a else None
        if current != render():
            print(f"{PAGE} is out of date: run python tools/config_reference.py", file=sys.stderr)
            return 1
        return 0
    write_section(PAGE, SECTION, render())
    print(f"wrote the key reference of {PAGE}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
