"""Running a stage's tasks on the Dask cluster: the one submit-and-wait loop with progress.

Every stage fans its work out as independent tasks (one per view, band,
material ...) and waits for all of them, reporting each one as it finishes
(``progress(done, total)``, which the flows turn into a progress bar or log
lines). A failed task re-raises its worker's error here, with the worker's
message, as soon as it is the next to finish (docs/architecture.md, "Execution").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from tasks.faults import kill_point

#: ``progress(done, total)``, called after each finished task.
Progress = Callable[[int, int], None]


def wait_all(futures: Sequence[Any], progress: Progress | None = None,
             weights: Sequence[int] | None = None) -> list[Any]:
    """Wait for ``futures`` as they finish; their results in the order given.

    Parameters
    ----------
    futures : sequence of distributed.Future
        Submitted tasks.
    progress : callable, optional
        ``progress(done, total)`` after each finished task.
    weights : sequence of int, optional
        Each task's share of the work (e.g. the views it writes); ``progress`` then counts
        those (``total = sum(weights)``) instead of tasks.

    Raises
    ------
    Exception
        The first failed task's error, as raised on its worker.
    """
    from distributed import as_completed

    share = {f.key: int(w) for f, w in zip(futures, weights)} if weights is not None else {}
    total = sum(share.values()) if weights is not None else len(futures)
    done = 0
    # on the futures' own client loop, not the default client's: a result lost with its worker (a cancelled
    # Slurm job) resets the future, whose event must belong to the loop that waits on it again
    loop = futures[0].client.loop if len(futures) else None
    for future in as_completed(futures, loop=loop):
        future.result()                              # re-raises the worker's error here
        done += share.get(future.key, 1)
        if progress is not None:
            progress(done, total)
        kill_point("chunk-done")
    return [f.result() for f in futures]


def run_all(client: Any, fn: Callable[..., Any], args: Sequence[tuple], progress: Progress | None = None,
            weights: Sequence[int] | None = None) -> list[Any]:
    """``fn(*a)`` for every ``a`` in ``args`` as one task each; the results in order (see :func:`wait_all`)."""
    return wait_all([client.submit(fn, *a, pure=False) for a in args], progress, weights)
