"""One BLAS thread for the ground station's numerical work, asked for cheaply.

`threadpoolctl.threadpool_limits` finds the process's BLAS libraries afresh on every call (0.8 ms: it walks
every loaded shared object). The survey asks for one thread around each surface fit and each step of the
mount's fit, hundreds of times a report, so the libraries are found once, here, and each request only sets
and restores the thread count (13 µs). Both of numpy's and scipy's OpenBLAS are loaded before the one search.
"""

from __future__ import annotations

import threading
from contextlib import AbstractContextManager

import numpy  # noqa: F401  (its BLAS, loaded before the search)
import scipy.linalg  # noqa: F401  (scipy's own BLAS, likewise)
from threadpoolctl import ThreadpoolController

_controller: ThreadpoolController | None = None
_lock = threading.Lock()


def one_blas_thread() -> AbstractContextManager:
    """A context in which BLAS runs on one thread; the caller's setting comes back on leaving it."""
    global _controller
    with _lock:
        if _controller is None:
            _controller = ThreadpoolController()
        controller = _controller
    return controller.limit(limits=1, user_api="blas")
