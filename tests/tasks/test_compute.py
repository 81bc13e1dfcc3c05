"""tasks.compute: the one submit-and-wait loop, on the session's real Dask cluster."""

from __future__ import annotations

import pytest

from tasks.compute import run_all, wait_all


def _square(x: int) -> int:
    return x * x


def _fail_on(x: int, bad: int) -> int:
    if x == bad:
        raise ValueError(f"task {x} failed on its worker")
    return x


def test_run_all_returns_results_in_order_and_reports_every_task(dask_client) -> None:
    seen = []
    out = run_all(dask_client, _square, [(i,) for i in range(7)], lambda done, total: seen.append((done, total)))
    assert out == [i * i for i in range(7)]
    assert [d for d, _ in seen] == list(range(1, 8)) and {t for _, t in seen} == {7}


def test_weights_count_work_not_tasks(dask_client) -> None:
    seen = []
    run_all(dask_client, _square, [(1,), (2,), (3,)], lambda d, t: seen.append((d, t)), weights=[5, 1, 2])
    assert seen[-1] == (8, 8) and all(t == 8 for _, t in seen)
    assert sorted(b - a for (a, _), (b, _) in zip([(0, 8)] + seen, seen)) == [1, 2, 5]


def test_a_failed_task_raises_its_workers_error(dask_client) -> None:
    futures = [dask_client.submit(_fail_on, i, 2, pure=False) for i in range(4)]
    with pytest.raises(ValueError, match="task 2 failed on its worker"):
        wait_all(futures)
