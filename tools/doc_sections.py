"""Pages several tools regenerate: each tool owns one marked section of a page and rewrites only it.

    <!-- NAME:start -->
    ... what the tool wrote ...
    <!-- NAME:end -->

A section not yet on the page is appended; the rest of the page is left as it is.
"""

from __future__ import annotations

import re
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


def with_sections_of(old: str, new: str) -> str:
    """new, plus every marked section of old that new lacks (appended in old's order): a tool that
    rewrites a whole page (tools.reproduce) keeps the sections other tools own on it."""
    for m in re.finditer(r"<!-- ([A-Za-z0-9_.-]+):start -->.*?<!-- \1:end -->", old, flags=re.S):
        if markers(m.group(1))[0] not in new:
            new = new.rstrip("\n") + "\n\n" + m.group(0) + "\n"
    return new
