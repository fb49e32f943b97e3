"""`Execution.imap`: results in item order as they arrive, a bounded number of tasks ahead."""

from __future__ import annotations

import time

import pytest

from pa_cli.config import ExecutionConfig
from pa_cli.runtime.distributed import Execution, execution

N_ITEMS = 12


def _slow_first(item: int) -> int:
    """The earlier the item, the longer it takes: the tasks finish out of order."""
    time.sleep(0.05 * (N_ITEMS - item) / N_ITEMS)
    return item * item


def _consumed_ahead(run: Execution, item_bytes: float) -> tuple[list[int], int]:
    """(results, the most items taken from the generator beyond the results yielded)."""
    taken = []

    def items():
        for item in range(N_ITEMS):
            taken.append(item)
            yield item

    results, ahead = [], 0
    for result in run.imap(_slow_first, items(), item_bytes):
        results.append(result)
        ahead = max(ahead, len(taken) - len(results))
    return results, ahead


def test_imap_in_process_yields_each_result_before_taking_the_next_item():
    results, ahead = _consumed_ahead(Execution(), 0.0)
    assert results == [i * i for i in range(N_ITEMS)]
    assert ahead == 0
    assert Execution().map(_slow_first, range(N_ITEMS)) == results


@pytest.mark.slow
def test_imap_on_a_local_cluster_keeps_order_and_its_bound():
    with execution(ExecutionConfig(workers=2, memory_budget_gb=1.0)) as run:
        limit = run.max_in_flight(0.3e9)  # the budget allows 3 such tasks at once
        assert limit == 3
        results, ahead = _consumed_ahead(run, 0.3e9)
        assert results == [i * i for i in range(N_ITEMS)]
        assert 1 <= ahead <= limit
        assert run.map(_slow_first, range(N_ITEMS), 0.3e9) == results
