"""Where the parallel work of `pa` runs: in this process, on a local dask cluster, or on a scheduler.

`execution(config)` is a context manager that opens the place the tasks run for the duration of a
command: with `workers = 0` and no `scheduler_address` nothing is started and tasks run in this
process one after another; with `workers = N` a `dask.distributed.LocalCluster` of N worker
processes is started (and closed on exit); with `scheduler_address = "tcp://HOST:PORT"` the
running cluster there is used. Code that has independent tasks calls `current_execution().map(fn,
items, item_bytes)`: it returns `[fn(item) for item in items]`, in order, whichever way they ran.

Tasks travel to the workers by pickling: `fn` must be a module-level function and `items` hold
what a worker needs to do its part (small arrays, paths and indices of scans), never every point of
a sequence. `map` keeps at most as many tasks in flight as `memory_budget_gb` allows for their
estimated size (`item_bytes`), so the driver never holds all tasks' inputs and results at once.
"""

from __future__ import annotations

import contextvars
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, TypeVar

from pa_cli.config import ExecutionConfig, SolverConfig
from pa_cli.errors import InputError

Item = TypeVar("Item")
Result = TypeVar("Result")

GB = 1e9  # bytes per GB (decimal, as the memory budget is stated)
MIN_TASKS_IN_FLIGHT = 1  # always let at least one task run, whatever its estimated size


@dataclass
class Execution:
    """A place to run tasks: `client` (a dask.distributed Client) or None for this process."""

    client: Any = None
    memory_budget_gb: float = SolverConfig().memory_budget_gb

    @property
    def n_workers(self) -> int:
        """Worker processes of the cluster (1: this process)."""
        if self.client is None:
            return 1
        return max(len(self.client.scheduler_info().get("workers", {})), 1)

    def max_in_flight(self, item_bytes: float) -> int:
        """Tasks submitted at once: enough to keep every worker busy, as far as the budget allows."""
        by_budget = int(self.memory_budget_gb * GB // max(item_bytes, 1.0))
        return max(min(2 * self.n_workers, by_budget), MIN_TASKS_IN_FLIGHT)

    def map(self, fn: Callable[..., Result], items: Iterable[Item], item_bytes: float = 0.0,
            shared: Any = None) -> list[Result]:
        """`[fn(item) for item in items]`, in order; on the cluster when there is one. With `shared`
        (not None): `[fn(item, shared) for item in items]`, `shared` sent to every worker once.

        `items` may be a generator: it is consumed as tasks are submitted, at most
        `max_in_flight(item_bytes)` ahead of the results.
        """
        extra = () if shared is None else (shared,)
        if self.client is None:
            return [fn(item, *extra) for item in items]
        from distributed import as_completed

        if extra:
            extra = (self.client.scatter(shared, broadcast=True, hash=False),)
        limit = self.max_in_flight(item_bytes)
        results: dict[int, Result] = {}
        iterator = enumerate(items)
        pending = as_completed()
        index_of = {}
        for index, item in iterator:
            future = self.client.submit(fn, item, *extra, pure=False)
            index_of[future.key] = index
            pending.add(future)
            if pending.count() >= limit:
                break
        for future in pending:
            results[index_of.pop(future.key)] = future.result()
            future.release()
            for index, item in iterator:  # refill one slot
                new = self.client.submit(fn, item, *extra, pure=False)
                index_of[new.key] = index
                pending.add(new)
                break
        return [results[i] for i in range(len(results))]


_CURRENT: contextvars.ContextVar[Execution | None] = contextvars.ContextVar("pa_execution", default=None)


def current_execution() -> Execution:
    """The execution opened by the innermost `execution(...)`, else this process."""
    return _CURRENT.get() or Execution()


@contextmanager
def execution(config: ExecutionConfig, memory_budget_gb: float = SolverConfig().memory_budget_gb
              ) -> Iterator[Execution]:
    """Open the place tasks run (see the module docstring) and make it `current_execution()`."""
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
    token = _CURRENT.set(Execution(client, memory_budget_gb))
    try:
        yield _CURRENT.get()
    finally:
        _CURRENT.reset(token)
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
