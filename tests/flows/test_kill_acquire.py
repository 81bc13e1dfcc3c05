"""`btf acquire --adaptive` SIGKILLed at each of its kill points resumes from its step journal (issue 19, item 2).

One uninterrupted reference run; then the same command into another output, killed in turn before anything is
written (``store-creating``), once the empty journal is in place (``store-created``), after its second finished
step (``chunk-done:2``), after three more steps of its rerun (the two recorded replayed), before writing the
final plan (``file-writing``, once every step is recorded) and before renaming it into place
(``file-replace``); the last rerun completes replaying every recorded step. Every file equals the
reference's: the JSON files (journal, report, plans) without their CPU seconds (:data:`RUN_ATTRS`), the CSV
files and the figure byte for byte, the HTML page with the steps table's CPU column masked. A finished
run's rerun writes nothing; other inputs at the same output are refused unless ``--overwrite``.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from test_kill_matrix import Btf, _json, btf  # noqa: F401, F811  (btf: the fixture of the kill matrix)

#: Steps of the run: a target it never reaches, so it stops at this budget (3 start-design steps, 5 chosen).
BUDGET = 8


def _html(path: Path) -> str:
    """The page with the last cell (CPU seconds) of each row of the 9-column steps table masked."""
    def mask(row: re.Match) -> str:
        cells = re.findall(r"<td[^>]*>.*?</td>", row.group(0))
        return row.group(0) if len(cells) != 9 else "<tr>" + "".join(cells[:-1]) + "<td>CPU</td></tr>"
    return re.sub(r"<tr>.*?</tr>", mask, path.read_text())


def _content(path: Path) -> Any:
    """What must equal between two runs: JSON without run records, HTML with CPU masked, else the bytes."""
    if path.suffix == ".json":
        return _json(path)
    if path.suffix == ".html":
        return _html(path)
    return path.read_bytes()


def _files(out: Path) -> list[str]:
    return sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())


def _journal(out: Path) -> dict[str, Any]:
    return json.loads((out / "journal.json").read_text())


def test_acquire_resumes_after_a_kill_at_each_point(btf: Btf, acquisition_evaluation, model_report, tmp_path):
    truth = sorted((acquisition_evaluation[0].parent / "acquisition-database").glob("*-carpet.zarr"))[0]

    def args(out: Path, *more: Any) -> tuple[Any, ...]:
        return ("acquire", "--adaptive", "--target-error", "0.001", "--budget", BUDGET, "--truth", truth,
                "--model", model_report, "--class", "carpet", "--out", out, *more)

    reference, out = tmp_path / "reference" / "acq", tmp_path / "killed" / "acq"
    for path in (reference, out):
        path.parent.mkdir()
    summary = btf.ok(*args(reference)).summary()
    assert summary["shots"] == BUDGET and summary["stopped"] == "budget"
    assert summary["reused"] == {"steps": [0, BUDGET]} and not summary["finished_before"]
    files = _files(reference)
    assert "journal.json" in files and len([f for f in files if f.startswith("plans/")]) == 2 * BUDGET

    btf.killed("store-creating", *args(out))
    assert _files(out) == []                                        # nothing written
    btf.killed("store-created", *args(out))
    assert _files(out) == ["journal.json"] and _journal(out)["steps"] == []
    btf.killed("chunk-done:2", *args(out))
    first = _journal(out)["steps"]
    assert [s["step"] for s in first] == [0, 1] and not (out / "plan.json").exists()
    run = btf.killed("chunk-done:3", *args(out))                    # replays 2 steps, then 3 more steps
    assert "resuming after 2 recorded step(s)" in run.err
    steps = _journal(out)["steps"]
    assert len(steps) == 5 and steps[:2] == first                    # recorded steps kept as they were, CPU too
    # the 3 steps left, each with its plan files (step_NNN.json and .csv: a file-writing each), then plan.json
    btf.killed(f"file-writing:{2 * (BUDGET - 5) + 1}", *args(out))
    journal = _journal(out)
    assert len(journal["steps"]) == BUDGET and journal["steps"][:5] == steps and not journal["finished"]
    assert not [f for f in _files(out) if f.startswith("plan.") or f.startswith("report.")]
    btf.killed("file-replace", *args(out))                          # every step replayed, plan.json beside
    assert (out / ".plan.tmp.json").exists() and not (out / "plan.json").exists()
    summary = btf.ok(*args(out)).summary()
    assert summary["reused"] == {"steps": [BUDGET, BUDGET]} and not summary["finished_before"]
    assert _journal(out)["finished"] and _journal(out)["steps"][:5] == steps

    assert _files(out) == files, "files differ from the uninterrupted run's (leftovers?)"
    for name in files:
        assert _content(out / name) == _content(reference / name), name

    # a finished run: a rerun writes nothing and prints the same summary
    before = {name: (out / name).stat().st_mtime_ns for name in files}
    again = btf.ok(*args(out)).summary()
    assert again["finished_before"] and again["reused"] == {"steps": [BUDGET, BUDGET]}
    assert {k: v for k, v in again.items() if k != "finished_before"} == \
        {k: v for k, v in summary.items() if k != "finished_before"}
    assert {name: (out / name).stat().st_mtime_ns for name in files} == before

    # other inputs: refused naming what differs and the option; --overwrite discards the old run
    refused = btf(*args(out, "--seed", "1"))
    assert refused.code == 2 and "seed differ" in refused.err and "--overwrite" in refused.err, refused.err
    assert {name: (out / name).stat().st_mtime_ns for name in files} == before
    btf.killed("chunk-done:1", *args(out, "--seed", "1", "--overwrite"))
    assert _files(out) == ["journal.json", "plans/step_000.csv", "plans/step_000.json"]
    assert _journal(out)["inputs"]["seed"] == 1 and len(_journal(out)["steps"]) == 1


def test_a_probing_run_resumes_with_the_same_probes(btf: Btf, acquisition_evaluation, model_report, tmp_path):
    """``--predictor probes``: killed after a probe step and resumed, the steps (probes drawn, their estimate) and
    the report equal the uninterrupted run's: the step index says which steps are probes, and the draw is seeded."""
    truth = sorted((acquisition_evaluation[0].parent / "acquisition-database").glob("*-carpet.zarr"))[0]

    def args(out: Path) -> tuple[Any, ...]:
        return ("acquire", "--adaptive", "--target-error", "0.001", "--budget", 20, "--truth", truth, "--model",
                model_report, "--class", "carpet", "--predictor", "probes", "--no-compare", "--out", out)

    reference, out = tmp_path / "reference", tmp_path / "killed"
    btf.ok(*args(reference))
    steps = _journal(reference)["steps"]
    n0 = json.loads((reference / "report.json").read_text())["record"]["settings"]["n_start"]
    assert [s["step"] for s in steps if s["probe"]] == list(range(n0, 20, 3))
    btf.killed(f"chunk-done:{n0 + 2}", *args(out))                  # after the first probe and a chosen step
    summary = btf.ok(*args(out)).summary()
    assert summary["reused"] == {"steps": [n0 + 2, 20]} and summary["predictor"] == "probes"
    for name in ("journal.json", "report.json"):
        assert _json(out / name) == _json(reference / name), name
