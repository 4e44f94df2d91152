"""Run directories: the names of their files, and how a command writes a folder of results safely.

A run directory is one survey flight: the payload's sample log, the truth the SITL knows (absent
for a real flight), the stockpile mesh the LiDAR saw, the vehicle's MAVLink telemetry log and the
mission plan. A report directory is what the ground station made of one.

`OutputFolder` is how `fly`, `serve --out` and `report` write theirs, so runs never mix:
- **locked while written**: an exclusive `fcntl.flock` on `.pilescan.lock` inside the folder; a second
  writer is refused (exit 4) and told which process holds it. The kernel drops the lock when
  its holder dies, so a killed writer never leaves the folder locked.
- **refused when it holds another result** (any of its file names, or a killed writer's leftovers),
  unless `force`; `force` removes the old files, the marker first, before anything new is written.
- **atomic**: every file is written into `.partial/` and renamed into place at the end, the marker
  (truth.json, report.json) last, so a folder without its marker is visibly incomplete and a killed
  writer never leaves old and new files side by side.
- **no litter**: a writer that fails removes what it wrote and the folders it created.

`publish_file` does the same for a single file (`plan`): written beside, then linked into place.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
import time
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType

from firmware_py.core.cli import RunFailure, UserError

SAMPLES_FILE = "samples.pslog"
"""The payload's sample log (`firmware_py.core.samplelog`)."""
TRUTH_FILE = "truth.json"
"""What the SITL knows and a real flight does not: true volume, building, mission, seeds, energy."""
PILE_FILE = "pile.stl"
"""The stockpile mesh the emulated LiDAR ray traced, in the storage frame W."""
TLOG_FILE = "telemetry.tlog"
"""Every MAVLink frame the vehicle sent and received (pymavlink's `mavlogdump.py` reads it)."""
PLAN_FILE = "mission.waypoints"
"""The mission as QGC WPL 110, loadable by any ground station."""

RUN_FILES = (SAMPLES_FILE, PILE_FILE, TLOG_FILE, PLAN_FILE, TRUTH_FILE)
"""Every file a run directory may hold; TRUTH_FILE is its marker (written last)."""

LOCK_FILE = ".pilescan.lock"
"""Held (flock) by the process writing the folder; removed when it is done."""
STAGING_DIR = ".partial"
"""Where files are written before they are renamed into place; left behind only by a killed writer."""

_LOCK_ATTEMPTS = 50  # the lock file can vanish under us only when its holder just finished: retry


def _fsync_dir(path: Path) -> None:
    """Make renames and removals in path durable (a power cut must not bring the old truth back)."""
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _make_dirs(path: Path) -> list[Path]:
    """mkdir -p path; returns the folders this call created, outermost first (to remove on failure)."""
    missing = []
    p = path
    while not p.exists() and not p.is_symlink() and p != p.parent:
        missing.append(p)
        p = p.parent
    created = []
    try:
        for d in reversed(missing):
            try:
                d.mkdir()
                created.append(d)
            except FileExistsError:
                if not d.is_dir():
                    raise
        if not path.is_dir():  # a file (or a dangling link) where the folder should be: what mkdir would say
            raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(path))
    except OSError:  # no litter: the folders made before the one that failed go too
        _remove_dirs(created)
        raise
    return created


def _remove_dirs(created: list[Path]) -> None:
    """rmdir the folders a failed writer created, innermost first; a folder someone else filled stays."""
    for d in reversed(created):
        with contextlib.suppress(OSError):
            d.rmdir()


def holder_pid(lock_path: Path) -> int | None:
    """The pid the lock's holder wrote into the lock file (None: unknown)."""
    try:
        return int(lock_path.read_text().strip())
    except (OSError, ValueError):
        return None


def present(folder: Path, names: Iterable[str]) -> list[str]:
    """The result files (and a killed writer's staging folder) already in folder."""
    found = [n for n in names if (folder / n).exists() or (folder / n).is_symlink()]
    if (folder / STAGING_DIR).exists():
        found.append(f"{STAGING_DIR}/")
    return found


def _taken(folder: Path, found: list[str], what: str) -> UserError:
    """The refusal of an --out that holds another result (or what a killed writer left)."""
    files = [f for f in found if f != f"{STAGING_DIR}/"]
    unfinished = f"{STAGING_DIR}/, left by a writer that was stopped"
    if not files:
        held = f"holds an unfinished {what} ({unfinished})"
    else:
        held = f"already holds a {what} ({', '.join(files)})"
        if len(files) < len(found):
            held += f" and an unfinished one ({unfinished})"
    return UserError(f"{folder} {held}; choose another --out or pass --force")


_PROBE_PATIENCE_S = 0.5
"""How long a lock attempt retries before calling the folder busy: a writer holds the lock for the whole
run (seconds to hours), while `check_free`'s probe holds it for microseconds, so two probes, or a probe
and a writer, that collide must not refuse each other."""


def _flock_or_busy(fd: int) -> bool:
    """Take an exclusive flock on fd; False if another holder keeps it past _PROBE_PATIENCE_S."""
    deadline = time.monotonic() + _PROBE_PATIENCE_S
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)


def _busy_message(folder: Path) -> str:
    pid = holder_pid(folder / LOCK_FILE)
    return (f"{folder} is being written by another process" + (f" (pid {pid})" if pid is not None else "")
            + "; wait for it to finish or choose another --out")


def _refuse_if_locked(folder: Path) -> None:
    """RunFailure when another process holds folder's lock (a probe: takes and drops it if free)."""
    try:
        fd = os.open(folder / LOCK_FILE, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    except OSError:  # no lock file: nobody is writing (or we cannot tell; the real lock will)
        return
    try:
        free = _flock_or_busy(fd)
    except OSError:
        return
    finally:
        os.close(fd)  # closing drops the probe's lock
    if not free:
        raise RunFailure(_busy_message(folder))


def check_free(path: str | Path, names: Iterable[str], *, force: bool, what: str = "run") -> Path:
    """Refuse early (before any work) an --out that holds another result; returns the folder as a Path.

    `OutputFolder` checks again under its lock; this only saves a long computation from being wasted.
    """
    if not str(path).strip():  # Path("") is the current directory: never write there by accident
        raise UserError(f"the {what} directory (--out) must be a non-empty path")
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise RunFailure(f"the {what} directory (--out) {folder} exists and is not a folder")
    if folder.is_dir():
        _refuse_if_locked(folder)
    if not force and folder.is_dir():
        found = present(folder, names)
        if found:
            raise _taken(folder, found, what)
    return folder


class OutputFolder:
    """A folder one command writes: locked, refused when taken, staged and renamed, marker last (module doc).

    with OutputFolder(out, RUN_FILES, TRUTH_FILE, force=force) as folder:
        write(folder.staged(SAMPLES_FILE)); ...
        folder.commit()
    """

    def __init__(self, path: str | Path, names: Iterable[str], marker: str, *, force: bool = False,
                 what: str = "run") -> None:
        self.path = check_free(path, (), force=True, what=what)  # the non-empty check only
        self.names = tuple(names)
        if marker not in self.names:
            raise ValueError(f"the marker {marker!r} must be one of the folder's names")
        self.marker = marker
        self.force = force
        self.what = what
        self.staging = self.path / STAGING_DIR
        self._lock_fd: int | None = None
        self._created: list[Path] = []
        self._published: list[Path] = []
        self._committed = False

    # ----- entering: create, lock, check, clear -----------------------------------------------------

    def __enter__(self) -> OutputFolder:
        try:
            self._lock()
            found = present(self.path, self.names)
            if found and not self.force:
                raise _taken(self.path, found, self.what)
            if found:
                self._clear()
            self.staging.mkdir()
        except BaseException:
            self._release(failed=True)
            raise
        return self

    def _lock(self) -> None:
        lock_path = self.path / LOCK_FILE
        for _ in range(_LOCK_ATTEMPTS):
            try:
                self._created += _make_dirs(self.path)
            except OSError as exc:  # a parent that cannot hold folders (/proc, a file), no permission, disk full;
                # a file at the path itself was refused by check_free in __init__
                raise RunFailure(f"cannot create the {self.what} directory (--out) {self.path}: "
                                f"{exc.strerror or exc}") from exc
            try:
                fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
            except FileNotFoundError:  # the folder was removed by a writer that failed just now
                continue
            try:
                free = _flock_or_busy(fd)
            except BaseException:
                os.close(fd)
                raise
            if not free:
                os.close(fd)
                raise RunFailure(_busy_message(self.path))
            try:
                same = os.stat(lock_path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if not same:  # its holder removed it as we opened it: that lock protects nothing now
                os.close(fd)
                continue
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            self._lock_fd = fd
            return
        raise RunFailure(f"could not lock {lock_path}: it keeps being removed by another process")

    def _clear(self) -> None:
        """--force: the old result goes, its marker first (durably), then the rest and any leftovers."""
        for name in (self.marker, *(n for n in self.names if n != self.marker)):
            p = self.path / name
            if p.is_dir() and not p.is_symlink():
                raise UserError(f"{p} is a directory; it is not a {self.what} file, so --force leaves it: "
                                "remove it yourself or choose another --out")
            p.unlink(missing_ok=True)
            if name == self.marker:
                _fsync_dir(self.path)
        if self.staging.exists():
            shutil.rmtree(self.staging)
        _fsync_dir(self.path)

    # ----- writing ------------------------------------------------------------------------------------

    def staged(self, name: str) -> Path:
        """Where to write `name` (one of the folder's names) before it is put in place."""
        if name not in self.names:
            raise ValueError(f"{name!r} is not a file of a {self.what} directory ({', '.join(self.names)})")
        return self.staging / name

    def publish(self, name: str) -> Path:
        """Put one staged file in place now (serve's plan, which a ground station loads while it runs)."""
        if name == self.marker:
            raise ValueError(f"the marker {name} is put in place last, by commit()")
        return self._move(name)

    def commit(self) -> None:
        """Put every staged file in place, the marker last; a file not among the names is a bug."""
        staged = sorted(p.name for p in self.staging.iterdir())
        unknown = [n for n in staged if n not in self.names]
        if unknown:
            raise RuntimeError(f"{self.what} writer staged files it does not declare: {unknown}")
        for name in staged:
            if name != self.marker:
                self._move(name)
        _fsync_dir(self.path)
        if self.marker in staged:
            self._move(self.marker)
            _fsync_dir(self.path)
        self._committed = True

    def _move(self, name: str) -> Path:
        src, dst = self.staging / name, self.path / name
        _fsync_file(src)
        os.replace(src, dst)
        self._published.append(dst)
        return dst

    # ----- leaving --------------------------------------------------------------------------------

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._release(failed=exc_type is not None or not self._committed)

    def _release(self, failed: bool) -> None:
        if failed:  # leave nothing of this attempt: no staged files, nothing published, no empty folders
            for p in self._published:
                with contextlib.suppress(OSError):
                    p.unlink()
        if self._lock_fd is not None:
            with contextlib.suppress(OSError):
                if self.staging.exists():
                    shutil.rmtree(self.staging)
            with contextlib.suppress(OSError):  # unlink while still holding it (see _lock's inode check)
                (self.path / LOCK_FILE).unlink()
            os.close(self._lock_fd)
            self._lock_fd = None
        if failed:
            _remove_dirs(self._created)


def publish_file(tmp: Path, dst: Path, *, force: bool) -> Path:
    """Move a fully written tmp to dst: atomically replacing it with force, else only if dst is absent
    (os.link fails on an existing name, so two writers cannot both win). tmp is gone afterwards."""
    try:
        _fsync_file(tmp)
        if force:
            os.replace(tmp, dst)
        else:
            try:
                os.link(tmp, dst)
            except FileExistsError:
                raise UserError(f"{dst} already exists; choose another --out or pass --force") from None
    finally:
        tmp.unlink(missing_ok=True)
    _fsync_dir(dst.parent)
    return dst
