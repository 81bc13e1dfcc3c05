"""What a run shows on stderr while it runs: progress of each stage, and the CLI's info lines.

A stage hands the update function of :func:`progress_bar` to
:func:`tasks.compute.wait_all` (through its ``tasks`` function), which calls it
after each finished task. One place decides how it is shown (:func:`on_terminal`):
in a terminal, a tqdm bar; elsewhere (a Slurm job log, CI, ``nohup``), one
timestamped line when the stage starts, about every 10 % of it and when it ends::

    2026-12-03 09:12:04 ingest: 40/96 views (42 %), 12.3 s

``btf --no-progress`` (or ``--quiet``) shows neither. Within a Prefect run the lines also go to the
run's log (:func:`run_log`), which a lasting Prefect server keeps and its UI shows
(docs/architecture.md, "Execution").
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:                     # importing tasks loads zarr: the CLI's first line comes before that
    from tasks.compute import Progress

#: Outside a terminal a stage prints a line each time another 1/STEPS of its work is done (besides its
#: first and last line, which say that it started and that it is done).
STEPS = 10

#: Plurals of the units that do not just take an "s".
_PLURALS = {"basis": "bases"}


def on_terminal() -> bool:
    """Whether stderr is a terminal: bars there, timestamped lines elsewhere (the one place that decides)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):             # replaced or closed stderr
        return False


def say(message: str, show: bool = True) -> None:
    """Print one info line on stderr (unless not ``show``), timestamped outside a terminal (a job log says
    when it happened); within a Prefect run, also send it to that run's log (:func:`run_log`)."""
    if show:
        print(message if on_terminal() else f"{_timestamp()} {message}", file=sys.stderr, flush=True)
    run_log(message)


#: The logger of :func:`run_log`: its one handler sends records to the Prefect API, nothing to stderr.
RUN_LOGGER = "btf.progress"


def run_log(message: str) -> None:
    """Send ``message`` at INFO to the log of the Prefect flow or task run this thread is in, where there
    is one: the UI's page of the run shows it. Prefect's handler sends it only when logging to the API
    is on, which :func:`flows.runtime.temporary_settings_of_run` turns on for a lasting server."""
    if "prefect" not in sys.modules:  # no run without Prefect; `btf --help` does not import it
        return
    import logging

    from prefect.context import FlowRunContext, TaskRunContext

    if FlowRunContext.get() is None and TaskRunContext.get() is None:
        return
    logger = logging.getLogger(RUN_LOGGER)
    if not logger.handlers:
        from prefect.logging.handlers import APILogHandler

        logger.addHandler(APILogHandler())
        logger.setLevel(logging.INFO)
        logger.propagate = False
    logger.info(message)


def _timestamp() -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S")


def _plural(unit: str, n: int) -> str:
    return unit if n == 1 else _PLURALS.get(unit, unit + "s")


class _Lines:
    """A stage's progress as log lines: at the start, at every further tenth of the work, at the end.

    A stage whose tasks report several runs in turn (one per store, each counting from 0) starts
    counting the tenths again at each one.
    """

    def __init__(self, desc: str, unit: str, show: bool = True):
        self.desc, self.unit, self.show = desc, unit, show
        self.start = time.perf_counter()
        self.done, self.total, self.step = 0, 0, 0
        say(f"{desc}: started", show)

    def _line(self, suffix: str = "") -> None:
        share = f" ({100 * self.done // self.total} %)" if self.total else ""
        say(f"{self.desc}: {self.done}/{self.total} {_plural(self.unit, self.total)}{share}, "
            f"{time.perf_counter() - self.start:.1f} s{suffix}", self.show)

    def update(self, done: int, total: int) -> None:
        if done < self.done or total != self.total:  # the next run of this stage
            self.step = 0
        self.done, self.total = done, total
        step = STEPS * done // total if total else 0
        if self.step < step < STEPS:
            self._line()
        self.step = max(self.step, step)

    def close(self) -> None:
        self._line(", done")

    def __enter__(self) -> _Lines:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def progress_bar(desc: str, enabled: bool, unit: str = "task") -> tuple[Any, Progress]:
    """The progress display of one stage and its ``update(done, total)``.

    Parameters
    ----------
    desc : str
        Name of the stage (e.g. ``"ingest"``).
    enabled : bool
        False shows nothing (``--no-progress``, ``--quiet``); the update function still works.
    unit : str
        What the stage's tasks count, singular (``"view"``, ``"material"``, ``"band"``, ``"basis"``).

    Returns
    -------
    bar : tqdm.tqdm or log lines
        Close it (or use it as a context manager) when the stage ends: outside a terminal that
        prints the last line.
    update : callable
        ``update(done, total)``: ``done`` of ``total`` units finished.
    """
    lines = _Lines(desc, unit, show=enabled and not on_terminal())  # also the Prefect run's log lines
    if not enabled or not on_terminal():
        return lines, lines.update
    from tqdm.auto import tqdm

    bar = tqdm(total=0, desc=desc, unit=unit, leave=True)

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()
        lines.update(done, total)

    return _Closing(bar, lines), update


class _Closing:
    """Closes several displays of one stage (a terminal's bar and the run log's lines) together; reads
    as the first (the bar: ``unit``, ``n``, ``total``)."""

    def __init__(self, *displays: Any):
        self.displays = displays

    def __getattr__(self, name: str) -> Any:
        return getattr(self.displays[0], name)

    def close(self) -> None:
        for display in self.displays:
            display.close()

    def __enter__(self) -> _Closing:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def in_parts(update: Progress, sizes: Sequence[int]) -> list[Progress]:
    """One display over consecutive runs (one per store, each counting from 0): the ``i``-th run's
    ``update(done, total)`` is shown as the ``sizes`` of the runs before it, plus the units of its own that
    it did not have to do (``sizes[i] - total``, reused), plus ``done``, of ``sum(sizes)``."""
    grand = int(sum(sizes))

    def part(before: int, size: int) -> Progress:
        return lambda done, total: update(min(before + max(size - total, 0) + done, grand), grand)

    return [part(int(sum(sizes[:i])), int(size)) for i, size in enumerate(sizes)]


@contextlib.contextmanager
def progress_bars(enabled: bool, units: Mapping[str, str] | None = None) -> Iterator[Callable[[str], Progress]]:
    """``bar(desc)`` opens the display of the next phase of a stage and returns its ``(done, total)``
    update (stages whose tasks report several phases in turn: bases, evaluation, ...). Opening a phase
    closes the one before (it has finished: its last line says how long it took); the last closes on exit.

    ``units`` names what each phase counts (``{"material bases": "material"}``; default ``"task"``).
    """
    bars = []

    def bar(desc: str) -> Progress:
        if bars:
            bars.pop().close()
        b, update = progress_bar(desc, enabled, unit=(units or {}).get(desc, "task"))
        bars.append(b)
        return update

    try:
        yield bar
    finally:
        for b in bars:
            b.close()
