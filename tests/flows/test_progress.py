"""Progress and info lines on stderr, the global options before and after the command, a fast first line."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from flows.cli import build_parser, main
from flows.progress import in_parts, progress_bar, progress_bars

ROOT = Path(__file__).resolve().parents[2]
#: ``2026-12-03 09:12:04 ingest: 40/96 views (42 %), 12.3 s``
STAMP = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d"


def test_outside_a_terminal_a_stage_prints_timestamped_lines_at_start_every_tenth_and_end(capsys):
    bar, update = progress_bar("ingest", True, unit="view")      # capsys: stderr is not a terminal
    with bar:
        for done in range(1, 97):
            update(done, 96)
    lines = capsys.readouterr().err.splitlines()
    assert all(re.match(STAMP + " ingest: ", line) for line in lines), lines
    assert lines[0].endswith("ingest: started")
    assert re.search(r"ingest: 96/96 views \(100 %\), \d+\.\d s, done$", lines[-1]), lines[-1]
    middle = lines[1:-1]
    assert len(middle) == 9 and re.search(r"ingest: 10/96 views \(10 %\), \d+\.\d s$", middle[0]), middle
    bar, update = progress_bar("ingest", False)                  # --no-progress: nothing at all
    with bar:
        update(1, 2)
    assert capsys.readouterr().err == ""


def test_each_phase_names_its_unit_and_ends_when_the_next_starts(capsys):
    with progress_bars(True, {"material bases": "material", "bases": "basis"}) as bar:
        bar("material bases")(1, 1)
        first = capsys.readouterr().err
        bar("bases")(2, 2)
        second = capsys.readouterr().err
        bar("evaluate")(3, 4)
    last = capsys.readouterr().err
    assert "material bases: 1/1 material (100 %)" in second and "bases: started" in second, (first, second)
    assert "bases: 2/2 bases (100 %)" in last and "evaluate: 3/4 tasks (75 %)" in last, last


def test_in_a_terminal_the_bar_counts_the_stage_unit(monkeypatch):
    monkeypatch.setattr("flows.progress.on_terminal", lambda: True)
    bar, update = progress_bar("build-db", True, unit="material")
    with bar:
        update(1, 3)
        assert bar.unit == "material" and (bar.n, bar.total) == (1, 3)


def test_global_options_are_accepted_after_the_command_too():
    parser = build_parser()
    before = parser.parse_args(["--no-progress", "--cluster", "a.yaml", "--log-level", "info", "ingest", "c.zarr",
                                "--out", "b.zarr"])
    after = parser.parse_args(["ingest", "c.zarr", "--out", "b.zarr", "--no-progress", "--cluster", "a.yaml",
                               "--log-level", "info"])
    assert vars(before) == vars(after)
    assert (after.no_progress, after.cluster, after.log_level, after.quiet) == (True, "a.yaml", "INFO", False)
    # an option given after the command wins; one not given there keeps the value from before it
    mixed = parser.parse_args(["--cluster", "a.yaml", "--quiet", "simulate", "--out", "o", "--cluster", "b.yaml"])
    assert (mixed.cluster, mixed.quiet, mixed.no_progress) == ("b.yaml", True, False)
    help_text = subprocess.run([sys.executable, "-m", "flows.cli", "ingest", "--help"], cwd=ROOT, capture_output=True,
                               text=True, timeout=60).stdout
    assert "global options (also accepted before the command)" in help_text and "--verbose" in help_text
    with pytest.raises(SystemExit) as refused:                   # errors only, yet info logs: a usage error
        main(["validate", "x.zarr", "--quiet", "--verbose"])
    assert refused.value.code == 2


def test_btf_help_imports_no_numerics_dask_or_prefect():
    """`btf --help` took seconds: building the parser imported scipy.ndimage and scikit-image."""
    code = ("import sys\nfrom flows.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted({m.split('.')[0] for m in sys.modules}))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    loaded = set(eval(out.stdout.strip().splitlines()[-1]))
    assert loaded.isdisjoint({"scipy", "skimage", "torch", "dask", "distributed", "prefect", "zarr"}), loaded
    assert "--quiet" in out.stdout and "--log-level" in out.stdout


@pytest.fixture()
def ingest_run(runtime_session, tiny_database, tmp_path):
    """``ingest_run(*options) -> (seconds to the first stderr line, exit code, stdout, stderr lines)``: a
    real `btf ingest` of a tiny capture in a subprocess, stderr a pipe (not a terminal), on the
    session's Prefect server and a one-worker threaded cluster, every global option after the command."""
    profile = tmp_path / "in-process.yaml"
    profile.write_text("cluster: {kind: local, n_workers: 1, threads_per_worker: 1, processes: false}\n")
    capture = sorted(tiny_database[1].glob("*.zarr"))[0]
    env = {**os.environ, "PREFECT_API_URL": runtime_session[1]}

    def run(*options: str) -> tuple[float, int, str, list[str]]:
        out = tmp_path / f"b{len(list(tmp_path.glob('*.zarr')))}.zarr"
        start = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "flows.cli", "ingest", str(capture), "--out", str(out),
                                 "--cluster", str(profile), *options], cwd=ROOT, env=env, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        first = proc.stderr.readline()
        seconds = time.perf_counter() - start
        stdout, rest = proc.communicate(timeout=240)
        return seconds, proc.returncode, stdout, [line for line in (first + rest).splitlines() if line]

    return run


def test_a_computing_command_says_what_starts_within_a_second_and_logs_its_stages(ingest_run):
    seconds, code, stdout, lines = ingest_run()
    assert code == 0, "\n".join(lines[-30:])
    assert json.loads(stdout)["stages"]["ingest"]["views_processed"] == 12
    assert seconds < 1.0, (seconds, lines[:1])
    assert re.fullmatch(STAMP + r" btf ingest: checking the inputs \.\.\.", lines[0]), lines
    assert re.fullmatch(STAMP + r" btf ingest: connecting to the Prefect API at http\S+ and starting a local Dask "
                        r"cluster \(1 worker x 1 thread, in this process; profile \S+in-process\.yaml\) \.\.\.",
                        lines[1]), lines
    assert any(re.match(STAMP + r" btf ingest: Prefect API \S+ and Dask cluster \S+ ready after", x) for x in lines)
    stage = [x for x in lines if re.match(STAMP + " ingest: ", x)]
    assert stage[0].endswith("ingest: started"), lines
    assert re.search(r"ingest: 12/12 views \(100 %\), \d+\.\d s, done$", stage[-1]), lines
    assert any(re.search(r"ingest: \d/12 views \(\d\d %\)", x) for x in stage[1:-1]), lines


def test_quiet_prints_only_errors_and_the_final_json(ingest_run):
    _, code, stdout, lines = ingest_run("--quiet")
    assert code == 0, "\n".join(lines[-30:])
    assert lines == [] and json.loads(stdout)["stages"]["ingest"]["views_processed"] == 12


def test_verbose_shows_prefect_and_dask_info_logs(ingest_run):
    _, code, _, lines = ingest_run("--verbose")
    assert code == 0, "\n".join(lines[-30:])
    assert any("distributed.scheduler - INFO" in x for x in lines), lines[:20]
    assert any("INFO" in x and "Flow run" in x for x in lines), lines[:40]


def test_a_stage_over_several_stores_counts_every_stores_views_once(capsys):
    """Three stores of 12 views in turn, the second reused whole (its run reports nothing) and the third
    half: one count of 36 views that only rises, at most one line per tenth, not 12-view counts restarting."""
    bar, update = progress_bar("ingest: 3 materials", True, unit="view")
    first, _, third = in_parts(update, [12, 12, 12])
    with bar:
        for done in range(1, 13):
            first(done, 12)
        for done in range(1, 7):                    # 6 of the third store's views were done before
            third(done, 6)
    lines = capsys.readouterr().err.splitlines()
    counts = [int(m.group(1)) for line in lines for m in [re.search(r": (\d+)/36 views", line)] if m]
    assert counts == sorted(counts) and counts[-1] == 36 and len(lines) <= 12, lines
    assert not any(re.search(r"/12 views", line) for line in lines), lines
