"""`Execution.imap`: results in item order as they arrive, a bounded number of tasks ahead."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from pa_cli.config import ExecutionConfig
from pa_cli.runtime.distributed import Execution, execution

N_ITEMS = 12


def _slow_first(item: int) -> int:
    """The earlier the item, the longer it takes: the tasks finish out of order."""
    time.sleep(0.05 * (N_ITEMS - item) / N_ITEMS)
    return item * item


def _where(item: int) -> tuple[int, int, bool]:
    """(the task's process id, item squared, whether the process ignores Ctrl-C)."""
    return os.getpid(), item * item, signal.getsignal(signal.SIGINT) == signal.SIG_IGN


def _marked(path: Path) -> None:
    """Takes a while, then leaves a file at `path`: which tasks ran."""
    time.sleep(0.1)
    path.touch()


def _consumed_ahead(run: Execution, item_bytes: float, holds_gil: bool = False) -> tuple[list[int], int]:
    """(results, the most items taken from the generator beyond the results yielded)."""
    taken = []

    def items():
        for item in range(N_ITEMS):
            taken.append(item)
            yield item

    results, ahead = [], 0
    for result in run.imap(_slow_first, items(), item_bytes, holds_gil=holds_gil):
        results.append(result)
        ahead = max(ahead, len(taken) - len(results))
    return results, ahead


def test_imap_in_process_yields_each_result_before_taking_the_next_item():
    results, ahead = _consumed_ahead(Execution(), 0.0)
    assert results == [i * i for i in range(N_ITEMS)]
    assert ahead == 0
    assert Execution().map(_slow_first, range(N_ITEMS)) == results


def test_imap_of_tasks_holding_the_gil_runs_them_on_processes_in_order_within_the_bound():
    """With `holds_gil` and 2 processes the tasks run in other processes, which ignore Ctrl-C (this process
    handles it), and come back in item order with at most 2 per process taken ahead; without `holds_gil`, or
    with one process, they run here."""
    run = Execution(processes=2)
    results, ahead = _consumed_ahead(run, 0.0, holds_gil=True)
    assert results == [i * i for i in range(N_ITEMS)]
    assert 1 <= ahead <= run.max_in_flight(0.0) == 4
    where = list(run.imap(_where, range(N_ITEMS), holds_gil=True))
    assert [square for _, square, _ in where] == results
    assert all(pid != os.getpid() and ignores for pid, _, ignores in where)
    assert 1 <= len({pid for pid, _, _ in where}) <= 2
    for here in (run.imap(_where, range(3)), Execution().imap(_where, range(3), holds_gil=True)):
        assert {pid for pid, _, _ in here} == {os.getpid()}


def test_interrupting_imap_on_processes_cancels_the_tasks_not_started(tmp_path):
    """Ctrl-C in the loop over the results (KeyboardInterrupt): the tasks not yet started are cancelled, the
    running ones end, and no task runs after the loop is left."""
    marks = [tmp_path / f"{i}.done" for i in range(40)]
    with pytest.raises(KeyboardInterrupt):
        for _ in Execution(processes=2).imap(_marked, marks, holds_gil=True):
            raise KeyboardInterrupt
    ran = sorted(tmp_path.iterdir())
    assert 1 <= len(ran) < len(marks) // 2
    time.sleep(0.3)
    assert sorted(tmp_path.iterdir()) == ran


@pytest.mark.slow
def test_imap_on_a_local_cluster_keeps_order_and_its_bound():
    with execution(ExecutionConfig(workers=2, memory_budget_gb=1.0)) as run:
        limit = run.max_in_flight(0.3e9)  # the budget allows 3 such tasks at once
        assert limit == 3
        results, ahead = _consumed_ahead(run, 0.3e9)
        assert results == [i * i for i in range(N_ITEMS)]
        assert 1 <= ahead <= limit
        assert run.map(_slow_first, range(N_ITEMS), 0.3e9) == results


def test_in_order_yields_the_threads_results_in_order_a_bounded_number_ahead():
    """`in_order`: the results of work finishing out of order come in order; while the consumer holds a result,
    at most two per thread more have started; an error of the work comes with its result."""
    import threading

    from pa_cli.runtime.distributed import in_order

    started: list[int] = []
    lock = threading.Lock()

    def work(j: int) -> int:
        with lock:
            started.append(j)
        return _slow_first(j)

    threads = 3
    for j, result in enumerate(in_order(work, N_ITEMS, threads)):
        assert result == j * j
        assert len(started) <= j + 1 + 2 * threads
        time.sleep(0.01)
    assert sorted(started) == list(range(N_ITEMS))

    def fails_at_five(j: int) -> int:
        if j == 5:
            raise ValueError("scan 5 unreadable")
        return j

    got = []
    with pytest.raises(ValueError, match="scan 5"):
        for result in in_order(fails_at_five, N_ITEMS, threads):
            got.append(result)
    assert got == [0, 1, 2, 3, 4]
