"""The architecture, checked: who may import whom, and no import cycles.

Every import statement of the installed packages is read with `ast` (those inside functions too,
so a lazy import cannot hide a dependency), resolved to a module of ours or to a top-level
distribution name, and held against the rules of the house.
"""

from __future__ import annotations

import ast
import functools
import graphlib
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("firmware_py", "sitl", "ground")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules(package: str) -> dict[str, Path]:
    return {_module_name(p): p for p in sorted((ROOT / package).rglob("*.py"))}


ALL = {name: path for pkg in PACKAGES for name, path in _modules(pkg).items()}


@functools.cache
def _imports(name: str, path: Path) -> frozenset[str]:
    """Absolute names of everything the module imports (relative imports resolved)."""
    tree = ast.parse(path.read_text(), str(path))
    is_pkg = path.name == "__init__.py"
    here = name.split(".") if is_pkg else name.split(".")[:-1]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join([*here[: len(here) - node.level + 1], *([base] if base else [])])
            out.add(base)
            out |= {f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in ALL}
    return frozenset(out)


def _ours(imported: str) -> str | None:
    """The module of ours an import names (the longest known prefix), or None for a third party."""
    parts = imported.split(".")
    for n in range(len(parts), 0, -1):
        candidate = ".".join(parts[:n])
        if candidate in ALL:
            return candidate
    return None


@functools.cache
def _graph() -> dict[str, set[str]]:
    """Each module of ours and the modules of ours it imports. Read when a test first asks, not at collection:
    every test worker collects this file, and one runs it."""
    return {name: {m for m in map(_ours, _imports(name, path)) if m and m != name} for name, path in ALL.items()}


@functools.cache
def _third_party() -> dict[str, set[str]]:
    """Each module of ours and the top-level distributions (or standard modules) it imports."""
    return {name: {i.split(".")[0] for i in _imports(name, path) if _ours(i) is None} for name, path in ALL.items()}


def test_that_the_shared_core_imports_only_numpy_and_the_standard_library():
    for name in _modules("firmware_py/core"):
        ours = {m for m in _graph()[name] if not m.startswith("firmware_py.core") and m != "firmware_py"}
        others = _third_party()[name] - set(sys.stdlib_module_names) - {"numpy", "__future__"}
        assert not ours and not others, f"{name} imports {sorted(ours | others)}"


def test_that_the_ground_station_imports_only_the_core_of_firmware_py():
    for name in _modules("ground"):
        bad = {m for m in _graph()[name] if m.startswith("firmware_py") and not m.startswith("firmware_py.core")
               and m != "firmware_py"}
        assert not bad, f"{name} imports {sorted(bad)}"
        assert not {m for m in _graph()[name] if m.startswith("sitl")}, f"{name} imports the simulator"


def test_that_the_payload_never_imports_the_simulator_or_the_ground_station():
    for name in _modules("firmware_py"):
        bad = {m for m in _graph()[name] if m.split(".")[0] in ("sitl", "ground")}
        assert not bad, f"{name} imports {sorted(bad)}"


def test_that_the_payload_needs_only_its_own_small_dependency_set():
    allowed = set(sys.stdlib_module_names) | {"__future__", "numpy", "pymavlink", "serial", "smbus2"}
    for name in _modules("firmware_py"):
        extra = _third_party()[name] - allowed
        assert not extra, f"{name} imports {sorted(extra)}, which the Raspberry Pi install does not have"


def test_that_no_module_imports_itself_through_a_cycle():
    try:
        tuple(graphlib.TopologicalSorter(_graph()).static_order())
    except graphlib.CycleError as exc:
        pytest.fail(f"import cycle: {' -> '.join(exc.args[1])}")
