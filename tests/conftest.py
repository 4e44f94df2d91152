"""Suite-wide test settings.

Hypothesis runs derandomized by default: the fuzz tests draw the same examples on every run, so a red CI
is a regression, never the luck of the draw (the project's no-flaky-tests rule). The regression examples
the fuzzers found are kept with `@example`. To explore new inputs, run with HYPOTHESIS_PROFILE=explore
(random draws, ten times the examples) and keep what it finds as new `@example`s.
"""

import os

try:
    from hypothesis import settings
except ImportError:  # a payload-only install without the test extras: no fuzz tests to configure
    settings = None

if settings is not None:
    settings.register_profile("ci", derandomize=True)
    settings.register_profile("explore", derandomize=False, max_examples=1000)
    settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
