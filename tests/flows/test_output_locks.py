"""Two writers of one output (issue 19): the second is refused naming the holder; a stale lock is taken over.

Two real `btf resample` processes racing for one output: tests/flows/test_kill_matrix.py
(``test_two_real_writers_of_one_output``, on that module's fork server and fixtures).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

import pytest

from tasks.locks import OutputLockedError, lock_path, output_locks


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_second_writer_is_refused_with_the_holders_identity(tmp_path):
    out = tmp_path / "db.zarr"
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock_path(out).write_text(json.dumps({"host": socket.gethostname(), "pid": holder.pid,
                                              "command": "btf ingest", "started": "2026-12-03T20:00:00"}))
        with pytest.raises(OutputLockedError, match=rf"db\.zarr is being written by another command \('btf ingest', "
                                                    rf"pid {holder.pid} on {socket.gethostname()}"):
            with output_locks([out], "btf resample"):
                pass
        assert json.loads(lock_path(out).read_text())["pid"] == holder.pid   # the holder's lock is untouched
    finally:
        holder.kill()


def test_a_dead_processes_lock_is_taken_over_and_released(tmp_path):
    out = tmp_path / "r.zarr"
    lock_path(out).write_text(json.dumps({"host": socket.gethostname(), "pid": _dead_pid(), "command": "btf x"}))
    with output_locks([out], "btf resample"):
        held = json.loads(lock_path(out).read_text())
        assert held["pid"] == os.getpid() and held["command"] == "btf resample"
    assert not lock_path(out).exists()


def test_a_lock_on_another_host_is_refused_with_the_way_out(tmp_path):
    out = tmp_path / "m"
    lock_path(out).write_text(json.dumps({"host": "node-17", "pid": 4242, "command": "btf build-db"}))
    with pytest.raises(OutputLockedError, match=r"pid 4242 on node-17.*delete .*m\.lock"):
        with output_locks([out], "btf build-db"):
            pass


def test_cli_refuses_a_second_writer_without_traceback(tmp_path, capsys):
    from flows.cli import main

    out = tmp_path / "carpet.png"
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock_path(out).write_text(json.dumps({"host": socket.gethostname(), "pid": holder.pid,
                                              "command": "btf render"}))
        code = main(["render", str(tmp_path / "x.zarr"), "--out", str(out)])
        err = capsys.readouterr().err
        assert code == 2, err
        assert f"pid {holder.pid}" in err and "Traceback" not in err
    finally:
        holder.kill()


@pytest.mark.parametrize("what", ["acquisition", "superres", "ingest"])
def test_evaluate_locks_report_json_only_where_it_writes_it(what, tmp_path, monkeypatch):
    """`btf evaluate acquisition|superres` write their reports into --out: two of them started in one
    folder must not lock each other out over ./report.json, which only `evaluate ingest` writes."""
    from flows.cli import _io_args, build_parser

    monkeypatch.chdir(tmp_path)
    args = build_parser().parse_args(["evaluate", what, "--db", "db", "--out", "eval"])
    outputs = _io_args(args)[0]
    assert "report.json" not in outputs.values() and "--out" in outputs
    given = build_parser().parse_args(["evaluate", what, "--out", "eval", "--report", "r.json"])
    assert _io_args(given)[0]["--report"] == "r.json"          # a path given is locked like any output
