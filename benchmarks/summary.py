"""The summary table of a `make bench` run: one line per bar, with its value, its goal and whether it is met.

Reads a folder of results, one benchmark each (``make bench`` writes them):

* ``NAME.json``: the benchmark's stdout, one JSON object whose ``"bars"`` lists its verdicts
  (:func:`_measure.bar`: ``measure``, ``value``, ``goal``, ``met``, ``issue``), or ``"skipped"`` with
  the reason (a benchmark that cannot run here, or one without a quick mode in ``make bench QUICK=1``);
* ``NAME.log``: its stderr, which ``make bench`` ends with ``exit status N after S s``.

A benchmark whose JSON is missing, empty or not a JSON object failed: it gets one line, the last line
of its log before the exit status (its error, usually), and counts as a bar not met. Prints the table
(benchmark, measure, value, goal, met: yes, no, n/a for a figure without a verdict, FAILED or
skipped), then one line counting the bars met, and writes the same rows to ``FOLDER/summary.json``.
Exits 1 when a benchmark failed, 0 otherwise (unmet bars are results, not errors).

Usage: ``python benchmarks/summary.py [FOLDER]`` (default ``bench-results``); ``make bench-summary``.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path


SUMMARY = "summary.json"
COLUMNS = ("benchmark", "measure", "value", "goal", "met")
_EXIT = re.compile(r"^exit status (\d+)")
#: Exit status when there are no results to summarise (the same code as `btf`'s bad input).
EXIT_NO_RESULTS = 2


def _last_words(log: Path) -> tuple[str, int | None]:
    """The last line of a benchmark's log before ``make bench``'s exit-status line, and that status."""
    lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()] \
        if log.is_file() else []
    status = None
    if lines and (m := _EXIT.match(lines[-1])):
        status = int(m.group(1))
        lines.pop()
    return (lines[-1] if lines else "no output"), status


def _result(path: Path) -> dict | None:
    """The benchmark's JSON object, or None when the file is missing, empty or not a JSON object."""
    try:
        result = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return result if isinstance(result, dict) else None


def benchmark_rows(folder: Path, name: str) -> list[dict]:
    """The table's rows for the benchmark ``name`` (its ``NAME.json`` and ``NAME.log`` in ``folder``)."""
    result = _result(folder / f"{name}.json")
    row = {"benchmark": name, "measure": "", "value": None, "goal": "", "met": None, "issue": None}
    if result is None:
        words, status = _last_words(folder / f"{name}.log")
        exit_text = f"exit status {status}" if status is not None else "no exit status"
        return [{**row, "status": "failed", "measure": f"failed ({exit_text}): {words}"[:160],
                 "log": str(folder / f"{name}.log")}]
    if "skipped" in result:
        return [{**row, "status": "skipped", "measure": f"skipped: {result['skipped']}"[:160]}]
    bars = result.get("bars")
    if not bars:
        return [{**row, "status": "no bars", "measure": "its result lists no bars"}]
    return [{**row, **{k: b.get(k) for k in ("measure", "value", "goal", "met", "issue")},
             "status": "measured"} for b in bars]


def collect(folder: Path) -> list[dict]:
    """Every benchmark's rows, benchmarks in name order: one per ``NAME.json`` or ``NAME.log`` in ``folder``."""
    names = sorted({p.stem for p in folder.glob("*.json") if p.name != SUMMARY} | {p.stem for p in folder.glob("*.log")})
    return [row for name in names for row in benchmark_rows(folder, name)]


def _value(value: float | None) -> str:
    if value is None:
        return "-"
    if abs(value) >= 100:
        return f"{value:.0f}"
    return f"{value:.1f}" if abs(value) >= 10 else f"{value:.3g}"


def _met(row: dict) -> str:
    if row["status"] in ("failed", "skipped"):
        return "FAILED" if row["status"] == "failed" else "skipped"
    return {True: "yes", False: "no", None: "n/a"}[row["met"]]


def counts(rows: list[dict]) -> dict:
    """Bars met, bars counted (with a verdict, a failed benchmark counting as one not met), and the rest."""
    return {"met": sum(r["met"] is True for r in rows),
            "counted": sum(r["met"] is not None or r["status"] == "failed" for r in rows),
            "failed": [r["benchmark"] for r in rows if r["status"] == "failed"],
            "skipped": [r["benchmark"] for r in rows if r["status"] == "skipped"],
            "without_verdict": sum(r["met"] is None and r["status"] in ("measured", "no bars") for r in rows)}


def table(rows: list[dict]) -> str:
    """The rows as an aligned text table, then the line counting the bars met."""
    cells = [COLUMNS] + [(r["benchmark"], r["measure"], _value(r["value"]) if r["status"] == "measured" else "-",
                          r["goal"] or "-", _met(r)) for r in rows]
    widths = [max(len(c[i]) for c in cells) for i in range(len(COLUMNS))]
    lines = ["  ".join(c.rjust(w) if i == 2 else c.ljust(w) for i, (c, w) in enumerate(zip(cell, widths))).rstrip()
             for cell in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    n = counts(rows)
    last = f"bars met: {n['met']} of {n['counted']}"
    if n["failed"]:
        last += f" ({len(n['failed'])} failed benchmark(s) counted as not met: {', '.join(n['failed'])})"
    if n["without_verdict"]:
        last += f"; {n['without_verdict']} figure(s) without a verdict (n/a)"
    if n["skipped"]:
        last += f"; {len(n['skipped'])} benchmark(s) skipped"
    return "\n".join(lines + [last])


def main(argv: list[str]) -> int:
    folder = Path(argv[0] if argv else "bench-results")
    if not folder.is_dir():
        print(f"summary.py: {folder}: no such folder of benchmark results; run `make bench` (or "
              "`make bench QUICK=1`) first, or name the folder that holds them", file=sys.stderr)
        return EXIT_NO_RESULTS
    rows = collect(folder)
    if not rows:
        print(f"summary.py: {folder}: no benchmark results (NAME.json or NAME.log) in it; run `make bench` "
              "first, or name the folder that holds them", file=sys.stderr)
        return EXIT_NO_RESULTS
    print(table(rows))
    (folder / SUMMARY).write_text(json.dumps({"folder": str(folder), "rows": rows, **counts(rows)}, indent=2))
    return 1 if counts(rows)["failed"] else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
