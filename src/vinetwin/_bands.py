"""Bands of image rows run on threads: the compiled per-pixel passes of perception, the D405
model and the depth readback (`vinetwin._cloud_kernels`, `render._sensor_kernels`,
`render._zbuffer_kernels`) split an image into bands of rows, run one in the calling thread
and the others on a pool of Python threads (the kernels release the GIL), and join the results
in row order.

Python threads rather than numba's parallel regions: with numba's parallel regions in
perception, the web app's click handler (a thread) spun for good in the test suite, and a
franky-sim Franka sharing the cores fell behind. The thread count is numba's
(`NUMBA_NUM_THREADS`; the executor's workers get one), so a process's passes use the cores
its ICP does.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import numpy.typing as npt

_POOL: tuple[int, ThreadPoolExecutor] | None = None
_POOL_LOCK = threading.Lock()


def threads() -> int:
    """Threads a pass may use: numba's thread count."""
    import numba

    return int(numba.get_num_threads())


def _pool(workers: int) -> ThreadPoolExecutor:
    """The process's band threads (made again in a forked child: threads do not fork)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL[0] != os.getpid() or _POOL[1]._max_workers < workers:
            _POOL = (os.getpid(), ThreadPoolExecutor(workers, "vinetwin-bands"))
        return _POOL[1]


def cuts(work: npt.NDArray[np.int64], bands: int) -> list[int]:
    """Row cuts of `bands` bands of about equal work, from the cumulative work before each row
    (H + 1 entries, non-decreasing)."""
    total = int(work[-1])
    inner = [int(np.searchsorted(work, total * b // bands)) for b in range(1, bands)]
    return [0, *inner, len(work) - 1]


def even(rows: int, bands: int) -> list[int]:
    """Row cuts of `bands` bands of equal height over `rows` rows."""
    return [rows * b // bands for b in range(bands + 1)]


def run(fn: Callable[..., Any], args: Sequence[Any], rows: Sequence[int]) -> list[Any]:
    """`fn(*args, v0, v1)` for each band of rows [rows[b], rows[b + 1]), the first in this
    thread and the others on the pool; their results in band order (an exception in a band is
    raised here)."""
    n = len(rows) - 1
    if n == 1:
        return [fn(*args, rows[0], rows[1])]
    pool = _pool(n - 1)
    futures = [pool.submit(fn, *args, rows[b], rows[b + 1]) for b in range(1, n)]
    first = fn(*args, rows[0], rows[1])
    return [first, *(f.result() for f in futures)]
