"""The command of a check that scores one function over the stored evaluation set and writes its table into a page's
section (`tools.echo_check`, `tools.contact_check`): the same options, refusals, progress and regenerate line for
each, so a new check states only its row, its table and its defaults."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from tools.doc_sections import write_evalset_section
from tools.evalset import DEFAULT_ROOT, runs_where
from tools.workers import progress_map, worker_pool


@dataclass(frozen=True)
class EvalsetCheck:
    """What a check is. prog: its name in messages ("echo_check"); section: the page section it writes; row: one
    stored run's row (None: nothing to score in it); summary: the table's lines from the rows; noises: the noise
    models it reads by default; p_traj: whether it takes --p-traj; no_rows: what it says when no chosen run gave a
    row."""

    prog: str
    section: str
    row: Callable[[str], dict | None]
    summary: Callable[[Sequence[dict]], list[str]]
    noises: tuple[str, ...]
    noise_help: str
    chunksize: int = 4
    p_traj: bool = False
    no_rows: str = "none of the chosen runs gave a row"


def check_main(check: EvalsetCheck, description: str | None, argv: Sequence[str] | None = None) -> int:
    """The check's command: 0 with its table printed (and written with --write), 2 with one line on stderr when an
    option is out of range or no run is there to score."""
    ap = argparse.ArgumentParser(prog=f"python -m tools.{check.prog}", description=description,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=DEFAULT_ROOT, help="the evaluation set (tools.evalset)")
    ap.add_argument("--noise", nargs="+", default=list(check.noises), help=check.noise_help)
    if check.p_traj:
        ap.add_argument("--p-traj", type=int, nargs="+", default=None, help="only these P_traj (percent)")
    ap.add_argument("--stride", type=int, default=1, help="every Nth run only (a quick look)")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--write", type=Path, default=None, metavar="PAGE",
                    help=f"also write the table into this page's section {check.section}")
    args = ap.parse_args(argv)
    p_traj = args.p_traj if check.p_traj else None
    if args.stride < 1 or args.jobs < 1:
        print(f"{check.prog}: --stride and --jobs must be >= 1", file=sys.stderr)
        return 2
    if not (args.root / "runs").is_dir():
        print(f"{check.prog}: no stored runs under {args.root} (python -m tools.evalset makes them)", file=sys.stderr)
        return 2
    dirs = runs_where(args.root, args.noise, p_traj)[::args.stride]
    if not dirs:
        print(f"{check.prog}: no stored runs with noise {' '.join(args.noise)} under {args.root}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    with worker_pool(args.jobs) as pool:
        rows = [r for r in progress_map(pool, check.row, dirs, desc=check.prog, unit="run", chunksize=check.chunksize)
                if r]
    if not rows:
        print(f"{check.prog}: {check.no_rows}", file=sys.stderr)
        return 2
    table = "\n".join(check.summary(rows))
    print(table)
    if args.write is not None:
        cmd = f"python -m tools.{check.prog}"
        cmd += f" --noise {' '.join(args.noise)}" if list(args.noise) != list(check.noises) else ""
        cmd += f" --p-traj {' '.join(map(str, p_traj))}" if p_traj else ""
        cmd += (f" --stride {args.stride}" if args.stride > 1 else "") + f" --jobs {args.jobs} --write {args.write}"
        write_evalset_section(args.write, check.section, cmd, len(rows), time.perf_counter() - t0, table)
    return 0
