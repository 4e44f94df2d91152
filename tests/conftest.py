"""Suite-wide test settings.

Hypothesis runs derandomized by default: the fuzz tests draw the same examples on every run, so a red CI
is a regression, never the luck of the draw (the project's no-flaky-tests rule). The regression examples
the fuzzers found are kept with `@example`. To explore new inputs, run with HYPOTHESIS_PROFILE=explore
(random draws, ten times the examples: tests/fuzz_budget.py) and keep what it finds as new `@example`s.

Every test process, and every program a test starts, runs one BLAS thread. `make test` runs four workers on
two cores; a threaded OpenBLAS spins its threads while it waits, so three processes of two spinning threads
each took the suite from 280 s to 386 s on one machine, and a coverage plan from 9 s to 29 s
(docs/design-notes.md, "One BLAS thread per test process").
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # for the programs the tests start (inherited)

try:
    from threadpoolctl import threadpool_limits
except ImportError:  # a payload-only install: no ground station, no threaded BLAS work to limit
    threadpool_limits = None
if threadpool_limits is not None:
    threadpool_limits(limits=1)  # for this process, whose numpy may have loaded its BLAS before this file

try:
    from hypothesis import settings
except ImportError:  # a payload-only install without the test extras: no fuzz tests to configure
    settings = None

if settings is not None:
    from tests.fuzz_budget import EXPLORE_FACTOR, profile_name  # tests stating a budget multiply it themselves

    settings.register_profile("ci", derandomize=True)
    settings.register_profile("explore", derandomize=False, max_examples=settings().max_examples * EXPLORE_FACTOR)
    settings.load_profile(profile_name())


def pytest_collection_modifyitems(config, items):
    """The modules marked `long` (the most test time: long lockstep flights, flights in real time) first, in
    their own order, then the rest in theirs. `make test` hands out whole files to four workers in
    collection order; the longest last left the other workers idle while one finished them. That order holds
    only with `--no-loadscope-reorder` (the Makefile's): by default xdist 3.8 hands out the files with the most
    tests first, which put the one-test real-time flights last and left two workers idle for 17 s."""
    items.sort(key=lambda item: item.get_closest_marker("long") is None)
