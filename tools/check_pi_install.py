"""The Raspberry Pi install, proved on the desktop: the payload installs and its tests pass without the simulator.

    python -m tools.check_pi_install [--keep DIR]      (or `make pi-check`)

1. builds the wheel (`pip wheel --no-deps`);
2. resolves `<wheel>[hw]` for the Pi (`pip download --only-binary=:all: --platform manylinux2014_aarch64
   --python-version 3.11`): every dependency must exist as an aarch64 wheel;
3. makes a fresh venv with only `pip install '<wheel>[hw]'` plus pytest and hypothesis, checks that the
   simulator's and the ground station's dependencies are really absent there (`import sitl.world.raycast`
   fails), then removes the wheel's `sitl/` and `ground/` packages, so a payload test that still imported
   them would skip or fail here rather than pass on the desktop's packages;
4. runs `pilescan-payload --help` and `--version`, and `pytest tests/firmware_py` from a copy of the tests
   in a temporary directory, where the checkout is not importable and `firmware_py` is the installed one.

Exit code 0 when all of it holds; the last line is the pytest summary.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PI_PLATFORM = ["--platform", "manylinux2014_aarch64", "--python-version", "3.11", "--only-binary=:all:"]
TEST_TOOLS = ["pytest>=8", "hypothesis>=6.100"]


class CheckFailed(RuntimeError):
    pass


def run(cmd: list[str], cwd: Path | None = None, expect_ok: bool = True) -> subprocess.CompletedProcess:
    """Run a step, echoing it; a failed step stops the check with its output."""
    print("$", " ".join(str(c) for c in cmd), flush=True)
    done = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True, env=clean_env())
    if expect_ok and done.returncode != 0:
        raise CheckFailed(f"{cmd[0]} failed ({done.returncode}):\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    return done


def clean_env() -> dict[str, str]:
    """This environment without PYTHONPATH/PYTHONHOME: with them, the payload venv would import the checkout
    (whose sitl/ and ground/ the check then deletes) instead of what it installed."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}


def build_wheel(work: Path) -> Path:
    out = work / "wheel"
    leftovers = [p for p in (ROOT / "build", *ROOT.glob("*.egg-info")) if not p.exists()]
    try:
        run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", out, ROOT])
    finally:  # setuptools builds in the checkout: leave it as it was
        for path in leftovers:
            shutil.rmtree(path, ignore_errors=True)
    (wheel,) = out.glob("pilescan-*.whl")
    return wheel


def download_for_pi(wheel: Path, work: Path) -> list[str]:
    dest = work / "aarch64"
    run([sys.executable, "-m", "pip", "download", "--quiet", *PI_PLATFORM, "-d", dest, f"{wheel}[hw]"])
    return sorted(p.name for p in dest.glob("*.whl"))


def payload_venv(wheel: Path, work: Path) -> Path:
    """A venv with the payload's install only; returns its python."""
    venv = work / "venv"
    run([sys.executable, "-m", "venv", venv])
    py = venv / "bin" / "python"
    run([py, "-m", "pip", "install", "--quiet", f"{wheel}[hw]", *TEST_TOOLS])
    for module in ("sitl.world.raycast", "ground.report"):  # their third-party deps must be missing
        if run([py, "-c", f"import {module}"], cwd=work, expect_ok=False).returncode == 0:
            raise CheckFailed(f"{module} imports in the payload-only venv: a simulator dependency leaked into [hw]")
    site = Path(run([py, "-c", "import firmware_py, os; print(os.path.dirname(firmware_py.__path__[0]))"],
                    cwd=work).stdout.strip())
    if not site.resolve().is_relative_to(venv.resolve()):
        raise CheckFailed(f"the payload venv imports firmware_py from {site}, outside {venv}: refusing to delete there")
    for package in ("sitl", "ground"):
        shutil.rmtree(site / package)
        if run([py, "-c", f"import {package}"], cwd=work, expect_ok=False).returncode == 0:
            raise CheckFailed(f"{package} is still importable in the payload-only venv")
    return py


def run_payload_tests(py: Path, work: Path) -> str:
    """pytest tests/firmware_py from a copy outside the checkout; returns the summary line."""
    tree = work / "run"
    shutil.copytree(ROOT / "tests" / "firmware_py", tree / "tests" / "firmware_py",
                    ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("__init__.py", "conftest.py", "fuzz_budget.py"):  # the suite's settings: fuzzing derandomized, budgets
        shutil.copy(ROOT / "tests" / name, tree / "tests" / name)
    where = run([py, "-c", "import firmware_py; print(firmware_py.__file__)"], cwd=tree).stdout.strip()
    if not where.startswith(str(work / "venv")):
        raise CheckFailed(f"firmware_py came from {where}, not the payload-only venv")
    done = run([py, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir", tree, "tests/firmware_py"],
               cwd=tree, expect_ok=False)
    lines = [ln for ln in done.stdout.splitlines() if ln.strip()]
    summary = lines[-1] if lines else "(no output)"
    if done.returncode != 0:
        raise CheckFailed(f"pytest failed in the payload-only venv:\n{done.stdout[-6000:]}\n{done.stderr[-2000:]}")
    return summary


def check(work: Path) -> str:
    wheel = build_wheel(work)
    print(f"wheel: {wheel.name}")
    pi = download_for_pi(wheel, work)
    print(f"aarch64 wheels for [hw] ({len(pi)}): {', '.join(pi)}")
    py = payload_venv(wheel, work)
    payload = py.parent / "pilescan-payload"
    usage = run([payload, "--help"], cwd=work).stdout
    if "--mavlink" not in usage:
        raise CheckFailed("pilescan-payload --help does not show its options")
    print("pilescan-payload --help: ok;", run([payload, "--version"], cwd=work).stdout.strip())
    summary = run_payload_tests(py, work)
    counts = dict((k, int(n)) for n, k in re.findall(r"(\d+) (passed|skipped|failed|errors?)", summary))
    print(f"tests/firmware_py in the payload-only venv: {summary}")
    if not counts.get("passed"):
        raise CheckFailed("no test passed")
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keep", type=Path, help="work in DIR and keep it (default: a temporary directory)")
    args = parser.parse_args(argv)
    try:
        if args.keep:
            args.keep.mkdir(parents=True, exist_ok=True)
            check(args.keep.resolve())
        else:
            with tempfile.TemporaryDirectory(prefix="pilescan-pi-") as tmp:
                check(Path(tmp))
    except CheckFailed as exc:
        print(f"pi-check FAILED: {exc}", file=sys.stderr)
        return 1
    print("pi-check: ok")
    return 0


if __name__ == "__main__":
    sys.exit(main())
