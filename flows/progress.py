"""Progress bars of the flows: the ``progress(done, total)`` callbacks a stage's tasks report to.

A stage hands the update function to :func:`tasks.compute.wait_all` (through its
``tasks`` function), which calls it after each finished task; the bar is drawn on
stderr, or not at all with ``btf --no-progress`` (docs/architecture.md, "Execution").
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

from tasks.compute import Progress


def progress_bar(desc: str, enabled: bool) -> tuple[Any, Progress]:
    """One progress bar and its ``update(done, total)``.

    Parameters
    ----------
    desc : str
        Label of the bar (e.g. ``"ingest"``).
    enabled : bool
        False hides the bar (``--no-progress``); the update function still works.

    Returns
    -------
    bar : tqdm.tqdm
        The bar; close it (or use it as a context manager) when the stage ends.
    update : callable
        ``update(done, total)`` sets the bar to ``done`` of ``total`` tasks.
    """
    from tqdm.auto import tqdm

    bar = tqdm(total=0, desc=desc, unit="view", disable=None if enabled else True, leave=True)

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    return bar, update


@contextlib.contextmanager
def progress_bars(enabled: bool) -> Iterator[Callable[[str], Progress]]:
    """``bar(desc)`` opens one more progress bar and returns its ``(done, total)`` update; all close on exit
    (stages whose tasks report several phases: bases, evaluation, ...)."""
    bars = []

    def bar(desc: str) -> Progress:
        b, update = progress_bar(desc, enabled)
        bars.append(b)
        return update

    try:
        yield bar
    finally:
        for b in bars:
            b.close()
