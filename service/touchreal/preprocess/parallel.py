"""Both cores for the large kernels: a kernel over independent columns runs as column ranges, one on
the calling thread and the others on a small shared thread pool.

The kernels are numba functions compiled with ``nogil=True`` (and scipy's FFT, which releases the
GIL), so the ranges run truly in parallel. Small calls (a few taxels, the 5 ms hop of one taxel
block) stay on the calling thread: a hand-off costs some 10-50 us, more than their work.

Threads: ``TOUCHREAL_THREADS`` (:class:`~touchreal.settings.ProcessSettings`) if set (1 turns the pool off), else the CPUs this process may run
on (``os.sched_getaffinity``), at most :data:`MAX_THREADS`; a 1-CPU container runs everything on
the calling thread. Results do not depend on the thread count (ranges write disjoint columns).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache

from pydantic import ValidationError

from ..settings import ProcessSettings

MAX_THREADS = 4  #: upper bound of the default thread count
THREADS_ENV = "TOUCHREAL_THREADS"
WORK_SCALE = 1.0  #: multiplies every ``min_work`` (0: split every call that has more than one item; tests)


_override: list[int] = []  #: set_thread_count's value, if any


def set_thread_count(n: int | None) -> None:
    """Use ``n`` threads from now on (None: back to the default); for benchmarks comparing 1 and 2."""
    if n is not None and n < 1:
        raise ValueError("thread count must be >= 1")
    _override[:] = [] if n is None else [int(n)]


def thread_count() -> int:
    """Threads the large kernels use (>= 1): :func:`set_thread_count`'s, else :func:`default_thread_count`."""
    return _override[0] if _override else default_thread_count()


@lru_cache(maxsize=1)
def default_thread_count() -> int:
    """``TOUCHREAL_THREADS`` (read once), else the usable CPUs, at most :data:`MAX_THREADS`."""
    try:
        threads = ProcessSettings().threads
    except ValidationError:
        raise ValueError(f"{THREADS_ENV} must be a whole number from 0 to 256") from None
    if threads is not None:
        return max(1, threads)
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    return max(1, min(cpus, MAX_THREADS))


_inside = threading.local()  #: set while a thread runs a range: nested calls run serially (no pool deadlock)


@lru_cache(maxsize=None)
def _pool(workers: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="touchreal-kernel")


# a forked child has none of the parent's pool threads: it builds its own pool on first use
os.register_at_fork(after_in_child=_pool.cache_clear)


def split_run(kernel: Callable[[int, int], object], n: int, work: int, min_work: int = 200_000) -> None:
    """Run ``kernel(a, b)`` over ranges covering ``0 .. n`` (columns, taxels, taxel blocks), in
    parallel when the whole call's ``work`` (e.g. columns x samples) gives each thread at least
    ``min_work`` of it. The calling thread runs the first range; exceptions of any range are raised
    here. A call made inside a range (a block's kernel while blocks run in parallel) runs serially."""
    if n < 2 or work < 2 * min_work * WORK_SCALE:  # the common small call: no further checks
        kernel(0, n)
        return
    parts = min(thread_count(), n, int(work // max(min_work * WORK_SCALE, 1)))
    if parts <= 1 or getattr(_inside, "active", False):
        kernel(0, n)
        return
    bounds = [n * i // parts for i in range(parts + 1)]
    futures = [_pool(parts - 1).submit(_range, kernel, bounds[i], bounds[i + 1]) for i in range(1, parts)]
    try:
        _range(kernel, bounds[0], bounds[1])
    finally:
        for f in futures:
            f.result()


def _range(kernel: Callable[[int, int], object], a: int, b: int) -> None:
    _inside.active = True
    try:
        kernel(a, b)
    finally:
        _inside.active = False
