"""`benchmarks/summary.py`, the table of `make bench`, on hand-written results (no benchmark runs here:
speed is never measured in tests)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SUMMARY = ROOT / "benchmarks" / "summary.py"


def _summary(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SUMMARY), *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)


def _write_results(folder: Path) -> None:
    """One benchmark that meets its bar, one that misses one (beside a figure without a goal), one that
    failed (empty JSON, a traceback in its log, as `make bench` leaves them), one skipped."""
    (folder / "als.json").write_text(json.dumps({"benchmark": "als", "bars": [
        {"measure": "ALS GFLOP/s / GEMM GFLOP/s", "value": 0.83, "goal": ">= 0.8", "met": True, "issue": 21}]}))
    (folder / "als.log").write_text("[22:00:00 load 1.00] run 1\nexit status 0 after 40 s\n")
    (folder / "ingest.json").write_text(json.dumps({"benchmark": "ingest", "bars": [
        {"measure": "ingest MB/s / OpenCV loop MB/s (medians)", "value": 2.64, "goal": ">= 4", "met": False,
         "issue": 21},
        {"measure": "generation GB/s / disk write GB/s", "value": None, "goal": "none (recorded)", "met": None,
         "issue": 2}]}))
    (folder / "demo.json").write_text("")
    (folder / "demo.log").write_text("Traceback (most recent call last):\n  File \"x.py\", line 1\n"
                                     "subprocess.CalledProcessError: Command 'btf demo' returned 1.\n"
                                     "exit status 1 after 12 s\n")
    (folder / "scaling.json").write_text(json.dumps({"benchmark": "scaling", "skipped": "no Slurm: sinfo absent",
                                                     "bars": []}))


def test_summary_prints_one_line_per_bar_and_counts_the_bars_met(tmp_path: Path) -> None:
    _write_results(tmp_path)
    out = _summary(str(tmp_path))
    assert out.returncode == 1, out.stderr                    # a benchmark failed
    lines = out.stdout.splitlines()
    assert lines[0].split() == ["benchmark", "measure", "value", "goal", "met"]
    body = {line.split()[0] + " " + line.split()[-1]: line for line in lines[2:-1]}
    assert set(body) == {"als yes", "demo FAILED", "ingest no", "ingest n/a", "scaling skipped"}
    assert "0.83" in body["als yes"] and ">= 0.8" in body["als yes"]
    assert "2.64" in body["ingest no"] and ">= 4" in body["ingest no"]
    assert "exit status 1" in body["demo FAILED"] and "CalledProcessError" in body["demo FAILED"]
    assert "no Slurm" in body["scaling skipped"]
    assert lines[-1].startswith("bars met: 1 of 3 (1 failed benchmark(s) counted as not met: demo)")
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert (summary["met"], summary["counted"], summary["failed"], summary["skipped"]) == (1, 3, ["demo"], ["scaling"])
    assert [(r["benchmark"], r["status"], r["met"]) for r in summary["rows"]] == [
        ("als", "measured", True), ("demo", "failed", None), ("ingest", "measured", False),
        ("ingest", "measured", None), ("scaling", "skipped", None)]


def test_summary_of_a_folder_where_every_bar_is_met_exits_0_and_ignores_its_own_output(tmp_path: Path) -> None:
    _write_results(tmp_path)
    for name in ("demo", "ingest", "scaling"):
        for path in tmp_path.glob(f"{name}.*"):
            path.unlink()
    assert _summary(str(tmp_path)).returncode == 0
    again = _summary(str(tmp_path))                           # summary.json is not read as a benchmark
    assert again.returncode == 0 and again.stdout.splitlines()[-1] == "bars met: 1 of 1"


def test_summary_names_a_missing_or_empty_folder_without_a_traceback(tmp_path: Path) -> None:
    for folder in (tmp_path / "nowhere", tmp_path):
        out = _summary(str(folder))
        assert out.returncode == 2
        assert out.stderr.startswith(f"summary.py: {folder}: ") and "make bench" in out.stderr
        assert "Traceback" not in out.stderr


def test_bar_gives_plain_json_and_every_benchmark_reports_bars() -> None:
    spec = importlib.util.spec_from_file_location("_measure", ROOT / "benchmarks" / "_measure.py")
    measure = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(measure)
    verdict = measure.bar("x / y", np.float32(0.5), ">= 0.8", np.float64(0.5) >= 0.8, 21)
    assert json.loads(json.dumps(verdict)) == {"measure": "x / y", "value": 0.5, "goal": ">= 0.8", "met": False,
                                               "issue": 21}
    missing = [p.name for p in sorted((ROOT / "benchmarks").glob("bench_*.py")) if '"bars"' not in p.read_text()]
    assert not missing, f"benchmarks whose JSON has no \"bars\" (make bench's table misses them): {missing}"
