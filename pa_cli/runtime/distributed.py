"""Where the parallel work of `pa` runs: in this process, on a local dask cluster, or on a scheduler.

`execution(config)` is a context manager that opens the place the tasks run for the duration of a
command: with `workers = 0` and no `scheduler_address` nothing is started and tasks run in this
process one after another; with `workers = N` a `dask.distributed.LocalCluster` of N worker
processes is started (and closed on exit); with `scheduler_address = "tcp://HOST:PORT"` the
running cluster there is used. Code that has independent tasks calls `current_execution().map(fn,
items, item_bytes)`: it returns `[fn(item) for item in items]`, in order, whichever way they ran;
`current_execution().imap(...)` yields the same results one by one, for callers that fold them
as they arrive instead of holding them all.

Tasks that hold the GIL (a C++ library called from Python) gain nothing from threads; without a
cluster, `imap(..., holds_gil=True)` runs them on `processes` processes of this machine
(`execution.threads`; the standard library's process pool, started for the call with "spawn", so a
worker imports `pa_cli` afresh and shares no thread state with this process).

Tasks travel to the workers by pickling: `fn` must be a module-level function and `items` hold
what a worker needs to do its part (small arrays, paths and indices of scans), never every point of
a sequence. `map` and `imap` keep at most as many tasks in flight as `memory_budget_gb` allows for
their estimated size (`item_bytes`), so the driver never holds all tasks' inputs at once (nor, with
`imap`, all their results). `process_tree_rss_bytes()` is the memory this process and its local
workers hold now, for checks of what is about to be allocated against the budget. `in_order(work, n,
threads)` runs work that releases the GIL on threads of this process, its results in order.
"""

from __future__ import annotations

import contextvars
import signal
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from pa_cli.errors import InputError

if TYPE_CHECKING:  # the config sits above the runtime; only its type is named here
    from pa_cli.config import ExecutionConfig

Item = TypeVar("Item")
Result = TypeVar("Result")

GB = 1e9  # bytes per GB (decimal, as the memory budget is stated)
IN_PROCESS_BUDGET_GB = 8.0  # memory for tasks in flight outside execution() (execution.memory_budget_gb's default)
MIN_TASKS_IN_FLIGHT = 1  # always let at least one task run, whatever its estimated size


@dataclass
class Execution:
    """A place to run tasks: `client` (a dask.distributed Client) or None for this process."""

    client: Any = None
    memory_budget_gb: float = IN_PROCESS_BUDGET_GB
    processes: int = 1  # without a client: processes of this machine for tasks that hold the GIL

    @property
    def n_workers(self) -> int:
        """Processes tasks may run on: the cluster's workers, else `processes`."""
        if self.client is None:
            return self.processes
        return max(len(self.client.scheduler_info().get("workers", {})), 1)

    def spreads(self, n_items: int, min_per_process: int) -> bool:
        """Without a cluster, tasks that hold the GIL over `n_items` items gain from this machine's processes: at
        least two of them would get `min_per_process` items each (a process's start against the items' work)."""
        return self.client is None and min(self.processes, n_items // min_per_process) > 1

    def max_in_flight(self, item_bytes: float) -> int:
        """Tasks submitted at once: enough to keep every worker busy, as far as the budget allows."""
        by_budget = int(self.memory_budget_gb * GB // max(item_bytes, 1.0))
        return max(min(2 * self.n_workers, by_budget), MIN_TASKS_IN_FLIGHT)

    def imap(self, fn: Callable[..., Result], items: Iterable[Item], item_bytes: float = 0.0,
             shared: Any = None, holds_gil: bool = False) -> Iterator[Result]:
        """`fn(item)` for each item, yielded in item order as the results arrive; on the cluster
        when there is one, else in this process, or with `holds_gil` on `processes` processes of
        this machine (when more than one). With `shared` (not None): `fn(item, shared)`, `shared`
        sent to every worker once.

        `items` may be a generator: it is consumed as tasks are submitted. At most
        `max_in_flight(item_bytes)` tasks are submitted and not yet yielded, so the caller can
        fold the results as they come (the driver then holds one result at a time, plus the
        ones of the tasks in flight); the next task is submitted before a result is yielded, so
        the workers stay busy while the caller folds. Results come in item order whatever order
        the tasks finish in: a fold over them gives the same result every run.
        """
        extra = () if shared is None else (shared,)
        if self.client is not None:
            if extra:
                extra = (self.client.scatter(shared, broadcast=True, hash=False),)
            yield from _in_item_order(lambda item: self.client.submit(fn, item, *extra, pure=False), items,
                                      self.max_in_flight(item_bytes))
        elif holds_gil and self.processes > 1:
            from concurrent.futures import ProcessPoolExecutor
            from multiprocessing import get_context

            # Ctrl-C is this process's to handle (exit 130): the pool's processes ignore it, and the tasks not yet
            # started are cancelled; the running ones finish first (a process killed mid-task breaks the pool)
            pool = ProcessPoolExecutor(self.processes, mp_context=get_context("spawn"), initializer=signal.signal,
                                       initargs=(signal.SIGINT, signal.SIG_IGN))
            try:
                yield from _in_item_order(lambda item: pool.submit(fn, item, *extra), items,
                                          self.max_in_flight(item_bytes))
            finally:
                pool.shutdown(cancel_futures=True)
        else:
            for item in items:
                yield fn(item, *extra)

    def map(self, fn: Callable[..., Result], items: Iterable[Item], item_bytes: float = 0.0,
            shared: Any = None) -> list[Result]:
        """`[fn(item) for item in items]`, in order (`imap` collected; the same arguments)."""
        return list(self.imap(fn, items, item_bytes, shared))


def _in_item_order(submit: Callable[[Item], Any], items: Iterable[Item], limit: int) -> Iterator[Any]:
    """The results of the futures `submit(item)` (dask's or the standard library's), in item order, with at most
    `limit` submitted and not yet yielded; the next is submitted before a result is yielded. A future is
    dropped once its result is taken (a dask future then releases its result on the worker)."""
    iterator = iter(items)
    in_flight: deque = deque()
    for item in iterator:
        in_flight.append(submit(item))
        if len(in_flight) >= limit:
            break
    while in_flight:
        result = in_flight.popleft().result()
        for item in iterator:  # refill the slot
            in_flight.append(submit(item))
            break
        yield result


def in_order_in_flight(threads: int) -> int:
    """Items of `in_order` on `threads` threads submitted and not yet consumed, at most: two per thread and the one
    being consumed."""
    return 2 * threads + 1


def in_order(work: Callable[[int], Item], n: int, threads: int) -> Iterator[Item]:
    """work(0), ..., work(n - 1) computed by `threads` threads of this process, yielded in order, at most
    `in_order_in_flight(threads)` of them under way (memory stays bounded when the consumer is slower). For work
    that releases the GIL (numba kernels, numpy on large arrays, reading files)."""
    with ThreadPoolExecutor(max_workers=threads) as pool:
        yield from _in_item_order(lambda j: pool.submit(work, j), range(n), in_order_in_flight(threads))


def process_tree_rss_bytes() -> float:
    """Resident memory (bytes) of this process and of its child processes (the worker processes of a local
    cluster), what a memory budget on one machine counts; workers of a remote scheduler are not counted."""
    import psutil

    process = psutil.Process()
    total = process.memory_info().rss
    for child in process.children(recursive=True):
        try:
            total += child.memory_info().rss
        except psutil.Error:  # a child that ended meanwhile holds nothing
            continue
    return float(total)


_CURRENT: contextvars.ContextVar[Execution | None] = contextvars.ContextVar("pa_execution", default=None)


def current_execution() -> Execution:
    """The execution opened by the innermost `execution(...)`, else this process."""
    return _CURRENT.get() or Execution()


@contextmanager
def execution(config: ExecutionConfig) -> Iterator[Execution]:
    """Open the place tasks run (see the module docstring) and make it `current_execution()`, with the memory
    budget `config.memory_budget_gb`."""
    memory_budget_gb = config.memory_budget_gb
    client = cluster = None
    if config.scheduler_address is not None or config.workers > 0:
        from distributed import Client, LocalCluster

        if config.scheduler_address is not None:
            try:
                client = Client(config.scheduler_address, timeout="10s")
            except OSError as exc:
                raise InputError(f"cannot reach the dask scheduler at {config.scheduler_address} ({exc}); "
                                 "start one with `dask scheduler` or drop --scheduler.") from None
        else:
            per_worker = memory_budget_gb * GB / (config.workers + 1)  # the driver gets one share
            cluster = LocalCluster(n_workers=config.workers, threads_per_worker=config.threads_per_worker,
                                   processes=True, memory_limit=int(per_worker), dashboard_address=None)
            client = Client(cluster)
    token = _CURRENT.set(Execution(client, memory_budget_gb, processes=1 if client is not None else config.threads))
    try:
        yield _CURRENT.get()
    finally:
        _CURRENT.reset(token)
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
