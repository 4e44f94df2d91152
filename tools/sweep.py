"""A generic experiment-sweep engine: run many cases through one function, cache each finished case on disk.

Why: parameter sweeps (piles x P_traj x error models x ...) take hours; a sweep killed halfway must resume where it
stopped, use every core, and scale to a dask cluster without changing the experiment code. What a case computes is
the caller's business: `fn(case) -> list[dict]` returns the rows for one case.

Usage::

    cases = [Case.make("cell", pile=p, p_traj=t) for p in piles for t in (25, 50)]
    rows = run_sweep(cases, my_case_fn, Path("runs/cell-sweep"))          # all local cores
    rows = run_sweep(cases, my_case_fn, cache, jobs=1)                       # in-process, for a debugger
    rows = run_sweep(cases, my_case_fn, cache, dask_address="tcp://10.0.0.5:8786")
    write_rows_csv(rows, Path("runs/cell-sweep.csv"))

Cache layout (one directory per experiment; the key covers the case, NOT the code of `fn`, so after changing
what `fn` computes use a new cache directory or add a version parameter to the cases)::

    cache_dir/cases/<key>.json     {"case", "key", "fn", "rows", "elapsed_s", "software"}: a finished case
    cache_dir/failures/<key>.txt   the traceback of the last failed attempt (removed when the case succeeds)

Rows are stored as strict JSON: numpy scalars/arrays become Python numbers/lists, tuples become lists, non-string
dict keys become strings, and NaN/inf become null (None): a NaN volume means "no estimate", which null says in any
tool that reads JSON or CSV. Finite floats round-trip exactly. Rows returned by a first run are the same objects
a rerun reads back from the cache (they go through the same JSON), so results never depend on what was cached.

Every returned row is `{"group": ..., **params, **row}`: case columns first. A row key equal to a case parameter
(or "group") must carry the same value; a different value fails that case, since the row would then contradict
the case it is cached under.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import pickle
import platform
import re
import sys
import tempfile
import time
import traceback
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import CancelledError, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any, TypeVar

from tools.workers import limit_threads_env, worker_pool

try:  # POSIX only; without it cached() still is correct, it just may compute a key twice
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "Case",
    "SweepError",
    "cached",
    "content_key",
    "missing_cases",
    "read_rows_csv",
    "run_sweep",
    "write_rows_csv",
]

log = logging.getLogger(__name__)
T = TypeVar("T")

_MAX_MESSAGES = 5  # failure messages quoted in a SweepError
_KEY_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


# --------------------------------------------------------------------------------------------------- cases


def _scalar(name: str, value: Any) -> str | int | float | bool | None:
    """A case parameter as a JSON scalar: the key hashes its JSON, so anything else would not be stable."""
    if type(value).__module__ == "numpy" and hasattr(value, "item"):
        value = value.item()  # numpy scalar -> Python scalar (a 0-d array too)
    if value is None or isinstance(value, bool):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"case parameter {name}={value!r}: must be finite (NaN never equals itself)")
        return float(value)
    if isinstance(value, str):
        return str(value)
    raise TypeError(f"case parameter {name}={value!r}: must be a JSON scalar (str, int, float, bool, None), "
                    f"not {type(value).__name__}")


def content_key(obj: Any) -> str:
    """Stable 16-hex-digit sha256 of canonical JSON: a cache key for `cached()` built from what the value depends on.

    Canonical: sorted keys, no spaces, so dict order never matters; 1 and 1.0 hash differently (JSON tells them
    apart), as do True and 1.
    """
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Case:
    """One unit of work: a name for the group it belongs to and its parameters (JSON-serialisable scalars).

    Params are kept as sorted (key, value) pairs so a Case is hashable, picklable and its key independent of the
    order the parameters were given in. Build with `Case.make(group, **params)`.
    """

    group: str
    params: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.group, str) or not self.group:
            raise TypeError(f"Case.group must be a non-empty str, not {self.group!r}")
        pairs = [(str(k), _scalar(str(k), v)) for k, v in self.params]
        names = [k for k, _ in pairs]
        if len(set(names)) != len(names):
            raise ValueError(f"Case {self.group}: duplicate parameter names in {names}")
        if "group" in names:
            raise ValueError(f"Case {self.group}: 'group' is reserved for the case group, not a parameter")
        object.__setattr__(self, "params", tuple(sorted(pairs, key=lambda kv: kv[0])))

    @classmethod
    def make(cls, group: str, **params: Any) -> Case:
        return cls(group, tuple(params.items()))

    def get(self, key: str, default: Any = None) -> Any:
        for k, v in self.params:
            if k == key:
                return v
        return default

    def as_dict(self) -> dict[str, Any]:
        """{"group": ..., "params": {...}}: what the cache file stores, and what the key hashes."""
        return {"group": self.group, "params": dict(self.params)}

    @property
    def key(self) -> str:
        """Stable content hash: sha256 of the canonical JSON of group+params, first 16 hex digits."""
        return content_key(self.as_dict())

    @property
    def label(self) -> str:
        """Short human-readable name for messages: group[k=v, ...]."""
        return f"{self.group}[{', '.join(f'{k}={v!r}' for k, v in self.params)}]"


class SweepError(RuntimeError):
    """Some cases failed; the others finished and are cached, so a rerun retries only the failed ones."""

    def __init__(self, failures: list[tuple[Case, str]], n_total: int, cache_dir: Path, *, stopped: bool = False):
        self.failures = failures  # (case, one-line error), in the order they failed
        self.n_failed = len(failures)
        self.n_total = n_total
        lines = [f"{self.n_failed} of {n_total} case(s) failed"
                 + (" (fail_fast: stopped at the first)" if stopped else "")
                 + f"; finished cases are cached in {cache_dir}, rerun to retry only the failed ones"]
        lines += [f"  {case.label}: {msg}" for case, msg in failures[:_MAX_MESSAGES]]
        if self.n_failed > _MAX_MESSAGES:
            lines.append(f"  ... and {self.n_failed - _MAX_MESSAGES} more (tracebacks in {cache_dir / 'failures'})")
        super().__init__("\n".join(lines))


# --------------------------------------------------------------------------------------------------- JSON rows


def _jsonable(obj: Any, where: str) -> Any:
    """obj as plain JSON data (see the module docstring for the conversions); TypeError says where it failed."""
    if type(obj).__module__ == "numpy" and hasattr(obj, "tolist"):
        obj = obj.tolist()  # ndarray -> nested lists; numpy scalar -> Python scalar
    if obj is None or isinstance(obj, bool):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, str):
        return str(obj)
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v, f"{where}[{k!r}]") for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    raise TypeError(f"{where}: cannot store a {type(obj).__module__}.{type(obj).__qualname__} in the JSON cache "
                    "(rows may hold numbers, strings, bools, None, lists, dicts and numpy arrays/scalars)")


def _normalise_rows(rows: Any, case: Case) -> list[dict[str, Any]]:
    """Check fn's return value and make it JSON data; raise (failing the case) on anything the cache can't hold."""
    if not isinstance(rows, list | tuple) or not all(isinstance(r, Mapping) for r in rows):
        raise TypeError(f"the case function must return a list of dicts, not {type(rows).__name__}")
    out = [_jsonable(r, f"row {i}") for i, r in enumerate(rows)]
    fixed = {"group": case.group, **dict(case.params)}
    for i, row in enumerate(out):
        for k, v in row.items():
            if k in fixed and v != fixed[k]:
                raise ValueError(f"row {i} key {k!r}={v!r} contradicts the case's {k}={fixed[k]!r}")
    return out


@cache
def _software() -> dict[str, str | None]:
    """What produced a cache file: enough to tell stale results apart when reading old caches."""
    try:
        from importlib.metadata import version

        pilescan = version("pilescan")
    except Exception:
        pilescan = None
    return {"pilescan": pilescan, "python": platform.python_version()}


# --------------------------------------------------------------------------------------------------- atomic files


def _atomic_write(path: Path, data: bytes) -> None:
    """Write via a temp file in the same directory + fsync + os.replace: readers see the old file or the new one,
    never half of one, even if this process is killed mid-write (the dot-prefixed .tmp file is left behind then)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    """An exclusive advisory lock (flock) so concurrent workers wait for one computation instead of repeating it."""
    if fcntl is None:  # pragma: no cover
        yield
        return
    with open(path, "a+b") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


_KINDS = {"pickle": "pkl", "json": "json"}


def _dump(value: Any, kind: str) -> bytes:
    if kind == "pickle":
        return pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    return json.dumps(_jsonable(value, "value"), allow_nan=False).encode()


def _load(path: Path, kind: str, warn: bool = True) -> tuple[bool, Any]:
    """(True, value) for a readable cache file, (False, None) when missing or unreadable (logged, then recomputed)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return False, None
    try:
        return True, (pickle.loads(data) if kind == "pickle" else json.loads(data))
    except Exception as e:
        if warn:
            log.warning("cache file %s is unreadable (%s: %s); recomputing it", path, type(e).__name__, e)
        return False, None


def cached(cache_dir: Path, key: str, compute: Callable[[], T], *, kind: str = "pickle") -> T:
    """Memoise an expensive intermediate (e.g. a simulated flight shared by many cases) on disk.

    The file is `cache_dir/<key>.pkl` (kind="pickle", any picklable value) or `<key>.json` (kind="json", stored
    with the same conversions as rows; the JSON-decoded value is returned even on the first call so both calls
    agree). Written atomically (tmp file + os.replace); when two workers on one machine ask for the same key at
    once a file lock makes the second wait and read the first one's result; on a file system without working
    locks both compute and the last os.replace wins, which is still correct. An unreadable file is recomputed.
    Build keys with `content_key({...})` or `Case.key` so that they change whenever the inputs do.
    """
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {sorted(_KINDS)}, not {kind!r}")
    if not _KEY_RE.match(key):
        raise ValueError(f"cache key {key!r} must be a plain file name ([A-Za-z0-9._-], not starting with . or -)")
    cache_dir = Path(cache_dir)
    path = cache_dir / f"{key}.{_KINDS[kind]}"
    hit, value = _load(path, kind)
    if hit:
        return value
    cache_dir.mkdir(parents=True, exist_ok=True)
    with _file_lock(path.with_name(path.name + ".lock")):
        hit, value = _load(path, kind, warn=False)  # another worker may have finished it while we waited for the lock
        if hit:
            return value
        value = compute()
        data = _dump(value, kind)
        _atomic_write(path, data)
    return json.loads(data) if kind == "json" else value


# --------------------------------------------------------------------------------------------------- running one case


@dataclass
class _Outcome:
    """What one case attempt produced; crosses process boundaries, so plain data only (exc stays in-process)."""

    ok: bool
    rows: list[dict[str, Any]] = field(default_factory=list)
    elapsed_s: float = 0.0
    error: str = ""  # one line
    traceback: str = ""
    exc: BaseException | None = None


def _one_line(e: BaseException) -> str:
    first = (str(e).strip().splitlines() or [""])[0]
    msg = f"{type(e).__name__}: {first}" if first else type(e).__name__
    return msg if len(msg) <= 300 else msg[:297] + "..."


def _run_case(fn: Callable[[Case], Any], case: Case, limit_threads: bool, keep_exc: bool = False) -> _Outcome:
    """Run fn(case) and never raise: a failure is data, so one bad case can't take down a pool or a dask task."""
    t0 = time.perf_counter()
    try:
        if limit_threads:
            limit_threads_env()
            from threadpoolctl import threadpool_limits

            with threadpool_limits(1):  # covers BLAS/OpenMP loaded after the initializer (e.g. by fn's imports)
                rows = fn(case)
        else:
            rows = fn(case)
        rows = _normalise_rows(rows, case)
    except Exception as e:
        return _Outcome(False, elapsed_s=time.perf_counter() - t0, error=_one_line(e),
                        traceback=traceback.format_exc(), exc=e if keep_exc else None)
    return _Outcome(True, rows=rows, elapsed_s=time.perf_counter() - t0)


def _check_picklable(fn: Callable[..., Any], backend: str) -> None:
    """Fail up front, not in every worker: worker processes import fn by module and name."""
    hint = ("define the case function at module level in an importable module (not a lambda, a nested function, "
            "or in an interactive session); bind extra arguments with functools.partial or put them in the case "
            "params; or use jobs=1")
    try:
        pickle.dumps(fn)
    except Exception as e:
        raise ValueError(f"{backend} needs a picklable case function, and {fn!r} is not ({_one_line(e)}): "
                         f"{hint}") from e
    inner = getattr(fn, "func", fn)  # functools.partial
    if getattr(inner, "__module__", None) == "__main__" and not getattr(sys.modules["__main__"], "__file__", None):
        raise ValueError(f"{backend} workers cannot import {fn!r}: it lives in an interactive __main__; {hint}")


# --------------------------------------------------------------------------------------------------- the sweep


def _case_path(cache_dir: Path, key: str) -> Path:
    return cache_dir / "cases" / f"{key}.json"


def _read_done(cache_dir: Path, case: Case) -> tuple[list[dict[str, Any]] | None, str | None]:
    """(rows, None) for a finished case; (None, None) if not run yet; (None, reason) if its file is unusable."""
    path = _case_path(cache_dir, case.key)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None, None
    except OSError as e:
        return None, _one_line(e)
    try:
        rec = json.loads(data)
    except ValueError as e:  # bad JSON or not UTF-8
        return None, _one_line(e)
    if not isinstance(rec, dict) or rec.get("case") != case.as_dict():
        return None, "does not hold this case"
    rows = rec.get("rows")
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        return None, "no list of rows"
    return rows, None


def missing_cases(cases: Sequence[Case], cache_dir: Path) -> list[Case]:
    """The distinct cases a sweep would still compute (unreadable cache files count as missing): for dry runs."""
    out: dict[str, Case] = {}
    for c in cases:
        if c.key not in out and _read_done(Path(cache_dir), c)[0] is None:
            out[c.key] = c
    return list(out.values())


class _Book:
    """Parent-side bookkeeping: writes each finished case to the cache as it arrives, counts, drives the bar."""

    def __init__(self, cache_dir: Path, fn: Callable[..., Any], bar: Any):
        self.cache_dir = cache_dir
        self.fn_name = f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"
        self.bar = bar
        self.rows: dict[str, list[dict[str, Any]]] = {}
        self.failures: list[tuple[Case, str]] = []
        self.first_exc: BaseException | None = None

    def record(self, case: Case, out: _Outcome) -> bool:
        """Store one outcome; True if it was a success."""
        key = case.key
        fail_path = self.cache_dir / "failures" / f"{key}.txt"
        if out.ok:
            rec = {"case": case.as_dict(), "key": key, "fn": self.fn_name, "rows": out.rows,
                   "elapsed_s": round(out.elapsed_s, 6), "software": _software()}
            text = json.dumps(rec, allow_nan=False, indent=1)
            _atomic_write(_case_path(self.cache_dir, key), text.encode())
            self.rows[key] = json.loads(text)["rows"]  # exactly what a rerun will read back
            with contextlib.suppress(FileNotFoundError):
                fail_path.unlink()
        else:
            self.failures.append((case, out.error))
            if self.first_exc is None:
                self.first_exc = out.exc
            log.warning("case %s failed: %s", case.label, out.error)
            with contextlib.suppress(OSError):
                _atomic_write(fail_path, f"{case.label}\nkey {key}\n\n{out.traceback or out.error}\n".encode())
            self.bar.set_postfix(failed=len(self.failures), refresh=False)
        self.bar.update(1)
        return out.ok


def _run_local(todo: list[Case], fn: Callable[..., Any], book: _Book, jobs: int, fail_fast: bool) -> None:
    if jobs == 1:
        for case in todo:
            if not book.record(case, _run_case(fn, case, limit_threads=False, keep_exc=True)) and fail_fast:
                return
        return
    pool = worker_pool(min(jobs, len(todo)), start_method="spawn")
    try:
        futures = {pool.submit(_run_case, fn, case, True): case for case in todo}
        stop = False
        for fut in as_completed(futures):
            case = futures[fut]
            try:
                out = fut.result()
            except CancelledError:
                continue
            except BrokenProcessPool:  # every case not finished gets this; which one killed its worker is unknown
                out = _Outcome(False, error="not finished: a worker process died (killed, crashed or out of memory) "
                               "while this or another case ran, which stops the pool")
            except Exception as e:  # e.g. fn's result could not be unpickled
                out = _Outcome(False, error=f"worker process failed: {_one_line(e)}")
            if not book.record(case, out) and fail_fast and not stop:
                stop = True  # cancel what hasn't started; still cache what is already running
                for f in futures:
                    f.cancel()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _run_dask(todo: list[Case], fn: Callable[..., Any], book: _Book, address: str | None, client: Any,
              fail_fast: bool) -> None:
    try:
        import distributed
    except ImportError as e:
        raise ImportError("run_sweep(dask_address=...) needs dask.distributed: pip install 'dask[distributed]'") from e
    own = client is None
    if own:
        client = distributed.Client(address)
    token = uuid.uuid4().hex[:8]  # unique task keys: never collide with another sweep's tasks on a shared cluster
    futures = {}
    try:
        for case in todo:
            fut = client.submit(_run_case, fn, case, True, pure=False, key=f"sweep-{case.key}-{token}")
            futures[fut] = case
        for fut in distributed.as_completed(list(futures)):
            case = futures.pop(fut)
            try:
                out = fut.result()
            except Exception as e:  # fn could not be unpickled on the worker, KilledWorker, ...
                out = _Outcome(False, error=f"dask task failed: {_one_line(e)}")
            fut.release()
            if not book.record(case, out) and fail_fast:
                break
    finally:
        if futures:
            client.cancel(list(futures))
        if own:
            client.close()


def run_sweep(cases: Sequence[Case], fn: Callable[[Case], list[dict]], cache_dir: Path, *,
              jobs: int | None = None, dask_address: str | None = None, client: Any = None, progress: bool = True,
              desc: str = "sweep", fail_fast: bool = False) -> list[dict]:
    """Run fn on every case not already cached; return all rows (cached + new), in case order.

    Each returned row is {"group": ..., **params, **row} (case columns first). Duplicate cases run once and give
    their rows at each position. jobs=None -> os.cpu_count() spawned worker processes (one BLAS thread each);
    jobs=1 -> in-process, no pool (debuggable; with fail_fast the SweepError chains fn's own exception).
    dask_address -> distributed.Client(address), or pass an existing `client=`; jobs is then ignored. Results are
    cached by this process as they complete, so a killed sweep loses only the cases in flight. A failing case is
    recorded and the others go on; at the end a single SweepError reports the failures (fail_fast=True: raise
    after the first failure, still caching the cases already running).
    """
    cache_dir = Path(cache_dir)
    use_dask = dask_address is not None or client is not None
    if jobs is None:
        jobs = os.cpu_count() or 1
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, not {jobs}")
    if use_dask:
        _check_picklable(fn, "a dask sweep")
    elif jobs > 1:
        _check_picklable(fn, f"a sweep with jobs={jobs}")
    cases = list(cases)
    for c in cases:
        if not isinstance(c, Case):
            raise TypeError(f"cases must be Case objects (Case.make(group, **params)), not {type(c).__name__}")

    unique: dict[str, Case] = {}
    for c in cases:
        unique.setdefault(c.key, c)
    done: dict[str, list[dict[str, Any]]] = {}
    todo: list[Case] = []
    bad: list[str] = []
    for key, case in unique.items():
        rows, reason = _read_done(cache_dir, case)
        if rows is not None:
            done[key] = rows
        else:
            todo.append(case)
            if reason is not None:
                bad.append(f"{_case_path(cache_dir, key)} ({reason})")
    if bad:
        log.warning("%d cached case file(s) unusable, recomputing them; first: %s", len(bad), bad[0])
    backend = "dask" if use_dask else ("in-process" if jobs == 1 else f"{min(jobs, len(todo))} process(es)")
    log.info("%s: %d case(s), %d cached, %d to run%s", desc, len(unique), len(done), len(todo),
             f" ({backend})" if todo else "")

    from tqdm.auto import tqdm

    with tqdm(total=len(unique), initial=len(done), desc=desc, unit="case", disable=None if progress else True,
              dynamic_ncols=True) as bar:
        book = _Book(cache_dir, fn, bar)
        if todo:
            (cache_dir / "cases").mkdir(parents=True, exist_ok=True)
            if use_dask:
                _run_dask(todo, fn, book, dask_address, client, fail_fast)
            else:
                _run_local(todo, fn, book, jobs, fail_fast)
    done.update(book.rows)
    if book.failures:
        raise SweepError(book.failures, len(unique), cache_dir, stopped=fail_fast) from book.first_exc

    out: list[dict] = []
    for case in cases:
        fixed = {"group": case.group, **dict(case.params)}
        out.extend({**fixed, **row} for row in done[case.key])
    return out


# --------------------------------------------------------------------------------------------------- CSV


def _csv_cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, float) and not math.isfinite(v):
        return "" if math.isnan(v) else repr(v)
    if isinstance(v, Mapping | list | tuple):
        return json.dumps(_jsonable(v, "cell"), allow_nan=False)
    return v


def write_rows_csv(rows: list[dict], path: Path) -> None:
    """Rows as CSV: the union of keys as columns in first-seen order, missing and None cells empty.

    Floats are written with repr, so finite ones read back exactly; NaN is written empty (reads back as None),
    lists/dicts as JSON text (read back as strings). Written atomically.
    """
    import csv
    import io

    columns: dict[str, None] = {}
    for r in rows:
        columns.update(dict.fromkeys(r))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), restval="", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: _csv_cell(v) for k, v in r.items()})
    _atomic_write(Path(path), buf.getvalue().encode())


_INT_RE = re.compile(r"^[+-]?\d+$")
_FLOAT_RE = re.compile(r"^[+-]?(\d+\.?\d*([eE][+-]?\d+)?|\.\d+([eE][+-]?\d+)?|inf|infinity|nan)$", re.IGNORECASE)


def _parse_cell(s: str) -> Any:
    if s == "":
        return None
    if _INT_RE.match(s):
        return int(s)
    if _FLOAT_RE.match(s):
        return float(s)
    if s in ("True", "False"):
        return s == "True"
    return s


def read_rows_csv(path: Path) -> list[dict]:
    """Rows from `write_rows_csv`: numbers parsed back to int/float, True/False to bool, '' to None.

    Strings that look like numbers come back as numbers: CSV keeps no types.
    """
    import csv

    with open(path, newline="", encoding="utf-8") as f:
        return [{k: _parse_cell(v) for k, v in r.items()} for r in csv.DictReader(f)]


def fresh_run_note(path: Path, all_computed: bool, wall_s: float, jobs: int, n_cases: int | None = None) -> str:
    """What the last run that computed every case took, for a generated page: this run records itself in
    path when it computed them all; a record for another number of cases (n_cases given) is not quoted."""
    if all_computed:
        record: dict[str, Any] = {"wall_s": wall_s, "jobs": jobs, "date": time.strftime("%Y-%m-%d")}
        if n_cases is not None:
            record["cases"] = n_cases
        path.write_text(json.dumps(record))
    try:
        f = json.loads(path.read_text())
        if n_cases is not None and f["cases"] != n_cases:
            return ""
        return (f"; the last run that computed all of them took {f['wall_s'] / 60:.1f} min with {f['jobs']} "
                f"worker(s) ({f['date']})")
    except (OSError, ValueError, KeyError, TypeError):
        return ""
