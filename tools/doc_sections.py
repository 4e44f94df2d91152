"""Pages several tools regenerate: each tool owns one marked section of a page and rewrites only it.

    <!-- NAME:start -->
    ... what the tool wrote ...
    <!-- NAME:end -->

A section not yet on the page is appended; the rest of the page is left as it is. Source files a tool writes
fitted constants into have a marked block of their own (`write_block`), which must already be there.
"""

from __future__ import annotations

import re
from datetime import date
from pathlib import Path


def markers(name: str) -> tuple[str, str]:
    return f"<!-- {name}:start -->", f"<!-- {name}:end -->"


def write_section(path: Path, name: str, text: str) -> None:
    """Replace section `name` of the page at path with text (markers added here), or append it."""
    start, end = markers(name)
    body = f"{start}\n{text.strip(chr(10))}\n{end}"
    old = path.read_text(encoding="utf-8") if path.exists() else ""
    a, b = old.find(start), old.find(end)
    if a >= 0 and b > a:
        new = old[:a] + body + old[b + len(end):]
    else:
        new = old.rstrip("\n") + ("\n\n" if old.strip() else "") + body
    path.write_text(new if new.endswith("\n") else new + "\n", encoding="utf-8")


def write_dated_section(path: Path, tool: str, text: str) -> None:
    """A benchmark tool's table in its own section of the page (named after the tool: `tools.bench_sitl` writes
    `bench-sitl`), headed by the command and today's date, so the page says when its figures were measured."""
    write_section(path, tool.rsplit(".", 1)[-1].replace("_", "-"),
                  f"`python -m {tool}` on {date.today().isoformat()}:\n\n{text}")


def with_sections_of(old: str, new: str) -> str:
    """new, plus every marked section of old that new lacks (appended in old's order): a tool that
    rewrites a whole page (tools.reproduce) keeps the sections other tools own on it."""
    for m in re.finditer(r"<!-- ([A-Za-z0-9_.-]+):start -->.*?<!-- \1:end -->", old, flags=re.S):
        if markers(m.group(1))[0] not in new:
            new = new.rstrip("\n") + "\n\n" + m.group(0) + "\n"
    return new


def write_block(path: Path, begin: str, end: str, body: str, tool: str) -> None:
    """Replace the text between the lines begin and end of the file at path (both kept) with body: the one block
    a calibration tool writes its fitted constants into. A file without exactly one such block is refused (the
    tool would otherwise write its constants nowhere, or twice)."""
    block = f"{begin}\n{body.strip(chr(10))}\n{end}"
    new, n = re.subn(re.escape(begin) + r".*?" + re.escape(end), lambda _: block, path.read_text(), flags=re.S)
    if n != 1:
        raise SystemExit(f"{tool}: {path} has {n} blocks between {begin!r} and {end!r}, not one: nothing written")
    path.write_text(new)
