"""The digest of the code a stored result was made with: a tool that keeps results to reuse them (a report it made
once) reuses one only when the code that would make it again is the same, so a table regenerated after a change is
made from the code as it is. Why: the pose oracle kept its reports and reused any it found, and a table it made
again after a session's changes still carried reports made by older code (docs/design-notes.md, "A stored report is
reused only when the code that made it is the code now")."""

from __future__ import annotations

import hashlib
from functools import lru_cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("ground", "firmware_py")
"""What a report is computed by: the ground station and the contracts it reads the log with."""


@lru_cache(maxsize=1)
def source_digest() -> str:
    """A digest of every Python file of PACKAGES (their paths and contents), once a process."""
    h = hashlib.blake2b(digest_size=16)
    for package in PACKAGES:
        for f in sorted((ROOT / package).rglob("*.py")):
            h.update(str(f.relative_to(ROOT)).encode())
            h.update(b"\0")
            h.update(f.read_bytes())
            h.update(b"\0")
    return h.hexdigest()


MADE_BY = "made-by-source"
"""The file beside a kept result that holds the digest of the code that made it."""


def made_by_this_code(folder: Path) -> bool:
    """Whether the result kept in `folder` was made by the code as it is now."""
    stamp = folder / MADE_BY
    return stamp.is_file() and stamp.read_text().strip() == source_digest()


def stamp_made_by_this_code(folder: Path) -> None:
    """Say in `folder` that its result was made by the code as it is now."""
    (folder / MADE_BY).write_text(source_digest() + "\n")
