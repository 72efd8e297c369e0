"""Threads that share one search's array work on the numpy backend (SearchParams.threads).

numpy releases the GIL while its products and scipy's FFTs run, so threads of one process run
them on separate cores. OpenBLAS's own threads do not mix with ours: after a product large
enough for it to share, its threads spin-wait for the next one, and a thread of ours then finds
its core taken (small products, too small for OpenBLAS to share, ran slower on 2 threads than
on 1 whenever a large product had run just before; session 18). So while a
search runs on several threads, BLAS is held to one thread (threadpoolctl) and the few large
products are split among ours instead (Workers.matmul: a batch by whole matrices, a single
product by columns). Without threadpoolctl a search stays on one thread.
"""

from __future__ import annotations

import contextlib
import functools
import math
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterator, TypeVar

import numpy as np

from mf_lpr_ros.optional import available, require

# Multiply-adds below which a share of a product is not worth handing to another thread: the
# hand-off costs ~0.15-0.2 ms on a 2-core VM, what one core multiplies ~8 M in. The prefilter's
# product at 1,500 references (5 M) took 0.14 ms on one thread and 0.30 split; two threads
# first won at ~27 M (docs/RESULTS.md, "Scale", session 57).
_MIN_WORK_PER_THREAD = 12_000_000

T = TypeVar("T")


class Workers:
    """A given number of threads, the caller's among them, for work split by worker number."""

    def __init__(self, threads: int = 1) -> None:
        self.threads = max(int(threads), 1) if available("threadpoolctl") else 1
        self._pool: ThreadPoolExecutor | None = None

    def run(self, work: Callable[[int], None]) -> None:
        """work(worker) for worker in 0 .. threads - 1, worker 0 on the calling thread; returns
        when all are done (re-raising the first error)."""
        if self.threads == 1 or getattr(_pool_thread, "busy", False):
            # Work handed out from a pool thread would wait for that thread: do it here.
            for worker in range(self.threads):
                work(worker)
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.threads - 1, thread_name_prefix="mf_lpr_search")
        others = [self._pool.submit(_on_pool_thread, work, worker)
                  for worker in range(1, self.threads)]
        try:
            work(0)
        finally:
            # Never return while a worker still writes into the caller's arrays.
            for other in others:
                other.exception()
        for other in others:
            other.result()

    def each(self, *tasks: Callable[[], T]) -> list[T]:
        """Every task's result, in order, task i run by worker i % threads (all of them by the
        calling thread when there is one)."""
        results: list = [None] * len(tasks)

        def work(worker: int) -> None:
            for index in range(worker, len(tasks), self.threads):
                results[index] = tasks[index]()

        self.run(work)
        return results

    def matmul(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """left @ right shared among the threads: by whole matrices of a stack both operands
        hold, when it has a matrix for each thread, else by right's columns (its last axis).
        A stack's matrices keep all their columns: a small map's 17 references split in two
        made each product too narrow to run at BLAS speed."""
        columns = right.shape[-1]
        stack = np.broadcast_shapes(left.shape[:-2], right.shape[:-2])
        work = math.prod(stack) * left.shape[-2] * left.shape[-1] * columns
        if self.threads == 1 or work < self.threads * _MIN_WORK_PER_THREAD:
            return left @ right
        out = np.empty(stack + (left.shape[-2], columns), dtype=np.result_type(left, right))
        by_matrix = (len(stack) == 1 and left.shape[:-2] == right.shape[:-2]
                     and stack[0] >= self.threads)
        bounds = np.linspace(0, stack[0] if by_matrix else columns,
                             self.threads + 1).round().astype(int)

        def multiply(worker: int) -> None:
            part = slice(bounds[worker], bounds[worker + 1])
            if by_matrix:
                np.matmul(left[part], right[part], out=out[part])
            else:
                np.matmul(left, right[..., part], out=out[..., part])

        self.run(multiply)
        return out

    @contextlib.contextmanager
    def own_cores(self) -> Iterator[None]:
        """BLAS held to one thread within, when this search runs on several of its own."""
        if self.threads == 1:
            yield
            return
        _hold_blas()
        try:
            yield
        finally:
            _release_blas()


_pool_thread = threading.local()


def _on_pool_thread(work: Callable[[int], None], worker: int) -> None:
    _pool_thread.busy = True
    try:
        work(worker)
    finally:
        _pool_thread.busy = False


# Searches of several indexes may overlap in one process: the first to start holds BLAS to
# one thread and the last to finish gives back the limits found before the first.
_blas_lock = threading.Lock()
_blas_holders = 0
_blas_limits_before = None


def _hold_blas() -> None:
    global _blas_holders, _blas_limits_before
    with _blas_lock:
        if _blas_holders == 0:
            _blas_limits_before = _blas_controller().limit(limits=1, user_api="blas")
        _blas_holders += 1


def _release_blas() -> None:
    global _blas_holders, _blas_limits_before
    with _blas_lock:
        _blas_holders -= 1
        if _blas_holders == 0:
            _blas_limits_before.restore_original_limits()
            _blas_limits_before = None


@functools.cache
def _blas_controller():
    """The process's native thread pools, found once (a scan of the loaded libraries)."""
    return require("threadpoolctl").ThreadpoolController()
