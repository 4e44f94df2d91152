# Two commands: `make demo` and `make test`. Each creates .venv on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

.PHONY: demo test lint bench pages pi-check clean

# uv installs the same packages from the same registry in 13 s where pip takes 46 s; where uv
# cannot be had (an offline mirror that lacks it, say) pip does the whole install. Byte-compiled, as pip does:
# the tests start many Python processes, and without .pyc files each compiles what it imports (pymavlink's
# dialect among them) again: the suite took 347 s instead of 285 s.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	( $(BIN)/python -m pip install --quiet uv && $(BIN)/uv pip install --quiet --compile-bytecode --python $(BIN)/python -e '.[dev]' ) \
	  || ( $(BIN)/python -m pip install --quiet --upgrade pip && $(BIN)/python -m pip install --quiet -e '.[dev]' )
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m tools.demo

# compileall: the suite starts many Python processes; where PYTHONDONTWRITEBYTECODE is set (CI machines) each
# one compiled the project's modules again (a fresh clone's suite: 289 s -> 271 s with them compiled once).
# The suite itself runs with bytecode writing on: pytest then keeps its rewritten test modules, which each of
# the five processes otherwise rewrites at collection (10.5 s -> 4.8 s a process).
# Four workers on two cores: the real-time tests (networked flights, MAVProxy, the signal tests, the browser) leave
# their worker idle for 149 s of the suite, which a fourth worker fills (287-299 s against 310-325 s with three,
# alternating runs on one machine; fresh clones 325 s with four, 308-330 s with three: the machine's hour-to-hour
# noise is as large as the gain; docs/design-notes.md, "The suite's time, measured again").
# The two collect-only runs first: on a fresh clone every worker rewrote the same 186 test modules' asserts at
# collection (13.3 s of CPU a worker against 4.6 s once pytest's rewritten modules are cached: 35 s of the suite's
# CPU on a fresh clone). Two processes on the two halves of tests/ write that cache once, in 8 s (14 s of CPU);
# their errors show in the real run, so they are silent here; a checkout that has the cache skips them
# (docs/design-notes.md, "The suite's first run").
test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m compileall -q firmware_py ground sitl tools
	ls tests/ground/__pycache__/*-pytest-*.pyc >/dev/null 2>&1 || \
	( PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest --collect-only -q -p no:cacheprovider tests/ground tests/tools \
	    >/dev/null 2>&1 & \
	  PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest --collect-only -q -p no:cacheprovider tests/firmware_py tests/sitl \
	    $(wildcard tests/test_*.py) >/dev/null 2>&1; wait ) || true
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -n 4 --dist loadfile --no-loadscope-reorder

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/python -m tools.bench_ground

pages: $(STAMP)  # every generated page again, after a change of the volumes (hours; resumable: tools/regenerate.py)
	$(BIN)/python -m tools.regenerate

pi-check: $(STAMP)  # the Raspberry Pi install: wheel, aarch64 resolution, payload-only venv and its tests
	$(BIN)/python -m tools.check_pi_install

clean:
	rm -rf $(VENV) build *.egg-info runs
