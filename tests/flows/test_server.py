"""``btf server start|status|stop``: a Prefect server that later commands reuse (real processes).

Each test has its own state folder (``XDG_STATE_HOME``), so that no running ``btf server`` of the
user's is touched or used, and stops what it started in a ``finally``.
"""

from __future__ import annotations

import datetime
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from btf_env import btf_environ, live_processes

from flows.server import (cluster_state_file, is_alive, recorded_server_url, running_server, server_cluster,
                          server_status, state_file, stop_server)

REPO = Path(__file__).resolve().parents[2]


def _btf(state_home: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flows.cli", *args], cwd=REPO, env=btf_environ(state_home),
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture()
def state_home(tmp_path, monkeypatch):
    """A private ``XDG_STATE_HOME``; any ``btf server`` started in it is stopped at the end."""
    home = tmp_path / "state"
    monkeypatch.setenv("XDG_STATE_HOME", str(home))
    try:
        yield home
    finally:
        state = server_status(state_file())
        stop_server(state_file())
        if isinstance(state.get("pid"), int) and is_alive(state["pid"]):  # pragma: no cover (stop failed)
            os.killpg(state["pid"], 9)


def _flow_runs_since(url: str, since: datetime.datetime) -> list[dict]:
    import httpx

    body = {"flow_runs": {"expected_start_time": {"after_": since.isoformat()}}, "limit": 50}
    response = httpx.post(f"{url}/flow_runs/filter", json=body, timeout=10)
    response.raise_for_status()
    return response.json()


def _logs_of(url: str, flow_run_id: str) -> list[dict]:
    import httpx

    body = {"logs": {"flow_run_id": {"any_": [flow_run_id]}}, "limit": 200}
    for _ in range(20):  # the client sends its logs in batches: the last ones may land after the run ends
        response = httpx.post(f"{url}/logs/filter", json=body, timeout=10)
        response.raise_for_status()
        if any("done" in log["message"] for log in response.json()):
            break
        time.sleep(0.5)
    return response.json()


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="checks the server's processes in /proc")
def test_server_start_status_is_used_then_stop_leaves_no_process(state_home, tmp_path):
    """One server for the whole story (a start costs seconds): start, status, a second start, a run with
    another profile (the server's API, its own cluster), runs on the server's cluster, stop."""
    started = _btf(state_home, "server", "start", "--timeout", "90")
    assert started.returncode == 0, started.stderr
    server = json.loads(started.stdout)
    assert server["status"] == "running" and server["started_now"] is True
    assert server["url"].startswith("http://127.0.0.1:") and server["host"] == "127.0.0.1"
    state = json.loads(Path(server["state_file"]).read_text())
    assert Path(server["state_file"]) == state_home / "btf-pipeline" / "server.json"
    assert set(state) == {"url", "pid", "port", "host", "log", "started"}  # no token, nothing secret
    assert is_alive(state["pid"])

    assert recorded_server_url() == running_server() == server["url"]
    status = _btf(state_home, "server", "status")
    assert status.returncode == 0 and json.loads(status.stdout)["status"] == "running"
    again = json.loads(_btf(state_home, "server", "start").stdout)
    assert again["started_now"] is False and again["pid"] == state["pid"]

    # a tiny computing command reports to it instead of starting a temporary server
    profile = tmp_path / "threaded.yaml"
    profile.write_text("cluster: {kind: local, n_workers: 1, threads_per_worker: 1, processes: false}\n")
    since = datetime.datetime.now(datetime.timezone.utc) - datetime.timedelta(seconds=5)
    out = tmp_path / "db"
    run = _btf(state_home, "--cluster", str(profile), "--no-progress", "simulate", "--device", "tiny",
               "--materials", "1", "--turntable", "1", "--texture-size", "8", "--out", str(out))
    assert run.returncode == 0, run.stderr
    assert server["url"] in run.stderr  # the run's log names the API it used
    assert "Starting temporary server" not in run.stderr
    runs = [r for r in _flow_runs_since(server["url"], since) if str(out) in json.dumps(r.get("parameters"))]
    assert runs and all(r["state_type"] == "COMPLETED" for r in runs), runs
    # ... and starts its own cluster, since its profile is not the one the server's cluster runs
    assert "not using the btf server's Dask cluster" in run.stderr and "cluster section of the profile" in run.stderr

    # with the server's profile, a command uses the server's Dask cluster, also with paths relative to
    # a folder its workers do not run in, and writes what a cluster of its own writes
    cluster = server["cluster"]
    assert cluster["status"] == "running" and cluster["address"].startswith("tcp://127.0.0.1:")
    capture = next(out.glob("*.zarr")).relative_to(tmp_path)
    shared = subprocess.run([sys.executable, "-m", "flows.cli", "--no-progress", "ingest", str(capture), "--out",
                             "shared.zarr"], cwd=tmp_path, env={**btf_environ(state_home), "PYTHONPATH": str(REPO)},
                            capture_output=True, text=True, timeout=300)
    assert shared.returncode == 0, shared.stderr
    assert f"Dask cluster {cluster['address']} (the btf server's) ready" in shared.stderr, shared.stderr
    # ... in a child of the server's command runner, which had the imports done
    runner = server["runner"]
    assert runner["status"] == "running"
    assert "forked by the btf server's command runner" in shared.stderr, shared.stderr
    # its progress lines reached the run's log on the server (the UI shows them), also with --no-progress
    ingest_runs = [r for r in _flow_runs_since(server["url"], since) if "shared.zarr" in json.dumps(r["parameters"])]
    assert len(ingest_runs) == 1, ingest_runs
    messages = [log["message"] for log in _logs_of(server["url"], ingest_runs[0]["id"])]
    assert any(m.startswith("ingest: started") for m in messages), messages
    assert any(re.fullmatch(r"ingest: 4/4 views \(100 %\), [\d.]+ s, done", m) for m in messages), messages
    own = _btf(state_home, "--cluster", str(profile), "--no-progress", "ingest", str(tmp_path / capture),
               "--out", str(tmp_path / "own.zarr"))
    assert own.returncode == 0, own.stderr
    assert "(the btf server's)" not in own.stderr
    chunks = [p.relative_to(tmp_path / "own.zarr") for p in (tmp_path / "own.zarr").rglob("*")
              if p.is_file() and "c" in p.relative_to(tmp_path / "own.zarr").parts]
    assert chunks and all((tmp_path / "shared.zarr" / c).read_bytes() == (tmp_path / "own.zarr" / c).read_bytes()
                          for c in chunks)

    # Ctrl-C (SIGINT to the command) reaches the forked run: it stops as a run in its own process does
    slow = subprocess.Popen([sys.executable, "-m", "flows.cli", "--no-progress", "simulate", "--device", "tiny",
                             "--materials", "6", "--out", str(tmp_path / "slow")], cwd=REPO,
                            env=btf_environ(state_home), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    for line in slow.stderr:
        lines.append(line)
        if "ready after" in line:
            break
    slow.send_signal(signal.SIGINT)
    rest = slow.communicate(timeout=120)[1]
    assert slow.returncode == 130, "".join(lines) + rest
    assert "interrupted; run the same command again to resume" in rest
    assert "forked by the btf server's command runner" in "".join(lines)

    stopped = _btf(state_home, "server", "stop")
    assert stopped.returncode == 0 and json.loads(stopped.stdout)["stopped_now"] is True
    assert not is_alive(state["pid"]) and live_processes(group=state["pid"]) == []
    assert not is_alive(cluster["pid"]) and live_processes(group=cluster["pid"]) == []
    assert not Path(cluster["state_file"]).exists()
    assert not is_alive(runner["pid"]) and not Path(runner["state_file"]).exists()
    assert not Path(runner["socket"]).exists()
    assert not Path(server["state_file"]).exists() and recorded_server_url() is None
    assert json.loads(_btf(state_home, "server", "status").stdout)["status"] == "stopped"


def test_a_stale_state_file_is_ignored_and_said_so(state_home, capsys):
    path = state_file()
    path.parent.mkdir(parents=True)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])  # a process id that is no longer in use
    dead.wait()
    path.write_text(json.dumps({"url": "http://127.0.0.1:9/api", "pid": dead.pid, "port": 9}))
    assert running_server() is None
    line = capsys.readouterr().err
    assert line.count("\n") == 1 and "ignoring" in line and str(path) in line and "not running" in line

    # a live process that is no Prefect server (its id reused) is not trusted either, nor signalled
    path.write_text(json.dumps({"url": "http://127.0.0.1:9/api", "pid": os.getpid(), "port": 9}))
    assert running_server() is None
    assert "ignoring" in capsys.readouterr().err
    assert stop_server()["stopped_now"] is False and not path.exists()  # removed, nothing killed


def test_a_stale_cluster_state_file_is_ignored_and_said_so(state_home, capsys):
    path = cluster_state_file()
    path.parent.mkdir(parents=True)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    path.write_text(json.dumps({"address": "tcp://127.0.0.1:9", "pid": dead.pid, "settings": {}}))
    assert server_cluster(lambda: {"cluster": {}}) is None
    line = capsys.readouterr().err
    assert line.count("\n") == 1 and "ignoring the btf server's Dask cluster" in line and "not running" in line
    assert server_status()["cluster"]["status"] == "stale"
    stop_server()
    assert not path.exists()


@pytest.mark.skipif(shutil.which("script") is None, reason="needs util-linux `script` for a terminal")
def test_no_telemetry_notice_in_a_terminal(tmp_path):
    """Prefect prints its first-run telemetry notice on `import prefect` in a terminal; the runtime's
    `quiet_logs` imports it with DO_NOT_TRACK set, so a first `btf` run shows none."""
    def first_run_in_a_terminal(code: str, home: Path) -> str:
        environ = {k: v for k, v in os.environ.items() if k not in ("DO_NOT_TRACK", "CI")}
        command = f"{shlex.quote(sys.executable)} -c {shlex.quote(code)}"
        return subprocess.run(["script", "-qec", command, "/dev/null"], cwd=REPO, capture_output=True, text=True,
                              env={**environ, "PREFECT_HOME": str(home)}, timeout=120).stdout

    assert "anonymous usage data" in first_run_in_a_terminal("import prefect", tmp_path / "a")  # the notice exists
    assert "anonymous usage data" not in first_run_in_a_terminal(
        "from flows.runtime import quiet_logs; quiet_logs()", tmp_path / "b")
