"""Prefect deployments and a process work pool (issue 16): ``btf deploy`` registers the deployments of a
``prefect.yaml`` with a real ``btf server``, a real ``prefect worker start`` runs them.

The server lives in a private state folder (``XDG_STATE_HOME``), as in ``tests/flows/test_server.py``,
and everything started here (server, its cluster, the worker and the worker's flow runs) is stopped by
process id at the end.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import httpx
import pytest
from btf_env import btf_environ, live_processes
import yaml

from flows.server import is_alive, start_server, stop_server

REPO = Path(__file__).resolve().parents[2]
#: One Dask worker thread in the run's own process: the runs here are tiny.
THREADED = "cluster: {kind: local, n_workers: 1, threads_per_worker: 1, processes: false}\n"
#: The runs' profile: threaded too, but not the server's, whose in-process cluster no run can join.
RUN_PROFILE = "cluster: {kind: local, n_workers: 1, threads_per_worker: 1, processes: false, memory_limit: 2GiB}\n"


def _stop_group(pid: int) -> None:
    """SIGTERM, then SIGKILL, the process group that ``pid`` leads."""
    for sig, wait in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(pid, sig)
        except ProcessLookupError:
            return
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline and is_alive(pid):
            time.sleep(0.2)


@pytest.fixture(scope="module")
def btf_server(tmp_path_factory):
    """``(url, environ)``: a ``btf server`` with its own Prefect database (``PREFECT_HOME``) in a private
    state folder, and the environment of the processes that use it."""
    root = tmp_path_factory.mktemp("deploy-server")
    profile = root / "threaded.yaml"
    profile.write_text(THREADED)
    environ = btf_environ(root / "state", PREFECT_HOME=str(root / "prefect-home"), PREFECT_UI_ENABLED="false")
    saved = dict(os.environ)
    os.environ.update(environ)  # the server's processes inherit it
    try:
        server = start_server(timeout=240, path=root / "state" / "btf-pipeline" / "server.json", profile=str(profile))
    finally:
        os.environ.clear()
        os.environ.update(saved)
    try:
        yield server["url"], environ
    finally:
        stop_server(root / "state" / "btf-pipeline" / "server.json")


@pytest.fixture(scope="module")
def tiny_database(tmp_path_factory) -> Path:
    """Two leather materials on the tiny dome (one turntable position, 8 x 8 texels), ingested."""
    from distributed import Client, LocalCluster

    from tasks.ingest import ingest_capture
    from tasks.simulate import SimulationConfig, simulate_database

    root = tmp_path_factory.mktemp("deploy-db")
    config = SimulationConfig(device="tiny", n_materials=2, seed=3, classes=("leather",), n_turntable=1,
                              texture_size=8)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False) as cluster, Client(cluster) as client:
        for capture in simulate_database(config, root / "captures", client).stores:
            ingest_capture(capture, root / "btf" / Path(capture).name, client)
    return root / "btf"


def _api(url: str, method: str, path: str, body: dict | None = None) -> object:
    """One call of the Prefect API; a 503 (its SQLite database busy with the runs' writes) is retried."""
    for _ in range(10):
        response = httpx.request(method, f"{url}{path}", json=body, timeout=20)
        if response.status_code != 503:
            break
        time.sleep(1.0)
    response.raise_for_status()
    return response.json() if response.content else None


def _runs_of(url: str, deployment_id: str) -> list[dict]:
    """The flow runs of a deployment, in the order they were due."""
    return _api(url, "POST", "/flow_runs/filter", {"flow_runs": {"deployment_id": {"any_": [deployment_id]}},
                                                    "sort": "EXPECTED_START_TIME_ASC", "limit": 50})


def _wait_for(what: str, check, timeout: float, logs: tuple[Path, ...], runs=lambda: []):
    """``check()``'s first true value within ``timeout`` s; else fail with the runs' states and the ends of
    ``logs`` (the worker's, the server's)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = check()
        if found:
            return found
        time.sleep(1.0)
    states = [(r["name"], r["state_name"], r["expected_start_time"], (r["state"] or {}).get("message")) for r in runs()]
    tails = "; ".join(f"{log.name}: {log.read_text(errors='replace')[-2000:]}" for log in logs if log.is_file())
    raise AssertionError(f"{what}: not within {timeout:.0f} s; runs: {states}; {tails}")


def test_a_scheduled_deployment_fires_on_a_worker_and_builds_incrementally(btf_server, tiny_database, tmp_path):
    url, environ = btf_server
    pool = f"btf-test-{uuid.uuid4().hex[:8]}"
    model = tmp_path / "model"
    profile = tmp_path / "run.yaml"
    profile.write_text(RUN_PROFILE)
    small = {"cluster": str(profile), "k_log_y": 4, "k_chroma": 2, "k_merged": 8}
    deployments = tmp_path / "prefect.yaml"
    deployments.write_text(yaml.safe_dump({"deployments": [
        {"name": "build-db-test", "entrypoint": "flows/deploy.py:build_db",
         "parameters": {"db": str(tiny_database), "out": str(model), **small},
         "schedules": [{"interval": 5}], "work_pool": {"name": "another-pool"}},
        {"name": "build-db-missing", "entrypoint": "flows/deploy.py:build_db", "concurrency_limit": 1,
         "parameters": {"db": str(tmp_path / "no-such-db"), "out": str(tmp_path / "model-2"), **small}},
    ]}))

    # btf deploy, with no PREFECT_API_URL: the running btf server's API, the pool created (--pool wins)
    deployed = subprocess.run([sys.executable, "-m", "flows.cli", "deploy", "--file", str(deployments),
                               "--pool", pool], cwd=tmp_path, env=environ, capture_output=True, text=True, timeout=120)
    assert deployed.returncode == 0, deployed.stderr
    result = json.loads(deployed.stdout)
    assert result["api"] == url and result["pools"] == result["created_pools"] == [pool]
    assert result["deployments"] == ["btf-build-db-run/build-db-test", "btf-build-db-run/build-db-missing"]
    assert f"PREFECT_API_URL={url} prefect worker start --pool {pool}" in deployed.stderr
    assert _api(url, "GET", f"/work_pools/{pool}")["type"] == "process"
    scheduled = _api(url, "GET", "/deployments/name/btf-build-db-run/build-db-test")
    assert [s["schedule"]["interval"] for s in scheduled["schedules"]] == [5.0]
    assert scheduled["work_pool_name"] == pool and scheduled["parameters"]["k_log_y"] == 4
    missing = _api(url, "GET", "/deployments/name/btf-build-db-run/build-db-missing")
    assert missing["global_concurrency_limit"]["limit"] == 1
    _api(url, "POST", f"/deployments/{missing['id']}/create_flow_run", {})
    # one run at a time on this pool: the builds share their output folder, and the machine has two cores
    _api(url, "PATCH", f"/work_pools/{pool}", {"concurrency_limit": 1})

    worker_log = tmp_path / "worker.log"
    logs = (worker_log, Path(environ["XDG_STATE_HOME"]) / "btf-pipeline" / "server.log")
    with open(worker_log, "wb") as log:
        worker = subprocess.Popen([sys.executable, "-m", "prefect", "worker", "start", "--pool", pool],
                                  cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                  start_new_session=True,
                                  env={**environ, "PREFECT_API_URL": url, "PREFECT_WORKER_QUERY_SECONDS": "2"})
    flow_runs: set[int] = set()
    try:
        def finished(deployment_id: str, n: int) -> list[dict] | None:
            flow_runs.update(live_processes(parent=worker.pid))
            runs = [r for r in _runs_of(url, deployment_id) if r["state_type"] in ("COMPLETED", "FAILED", "CRASHED")]
            return runs if len(runs) >= n else None

        # a failed run is visible as failed in the API, with the command's error as its message
        failed = _wait_for("the run on a missing database failed", lambda: finished(missing["id"], 1), 150,
                           logs)[0]
        assert failed["state_type"] == "FAILED", failed["state"]
        assert "no-such-db" in failed["state"]["message"], failed["state"]["message"]

        # the schedule fires; once a second run starts, no third is wanted
        def second_started() -> bool:
            flow_runs.update(live_processes(parent=worker.pid))
            return sum(r["state_type"] in ("RUNNING", "COMPLETED", "FAILED", "CRASHED")
                       for r in _runs_of(url, scheduled["id"])) >= 2

        _wait_for("a second scheduled run started", second_started, 150, logs,
                  lambda: _runs_of(url, scheduled["id"]))
        # no third: pause the schedule and cancel what is still waiting
        _api(url, "PATCH", f"/deployments/{scheduled['id']}", {"paused": True})
        for run in _runs_of(url, scheduled["id"]):
            if run["state_type"] in ("SCHEDULED", "PENDING"):
                _api(url, "POST", f"/flow_runs/{run['id']}/set_state",
                     {"state": {"type": "CANCELLED", "message": "test: two runs are enough"}, "force": True})
        runs = _wait_for("two scheduled runs finished", lambda: finished(scheduled["id"], 2), 120, logs,
                         lambda: _runs_of(url, scheduled["id"]))
    finally:
        deadline = time.monotonic() + 30  # a finished run's process sends its last logs as it exits
        while any(is_alive(pid) for pid in flow_runs) and time.monotonic() < deadline:
            time.sleep(0.5)
        _stop_group(worker.pid)
        for pid in flow_runs:
            if is_alive(pid):
                _stop_group(pid)
    assert all(r["state_type"] == "COMPLETED" for r in runs[:2]), [r["state"] for r in runs]
    assert all(r["auto_scheduled"] for r in runs[:2])

    # the first run fitted both materials, the second nothing new, and the report says so
    def messages_of(run: dict) -> list[str]:
        return [log["message"] for log in _api(url, "POST", "/logs/filter",
                                               {"logs": {"flow_run_id": {"any_": [run["id"]]}}, "limit": 200})]

    deadline = time.monotonic() + 30  # the API stores a run's logs in batches, after its state
    while (not any("done" in m for m in messages_of(runs[1]))) and time.monotonic() < deadline:
        time.sleep(0.5)
    messages = [messages_of(r) for r in runs[:2]]
    assert any("fitted 2 of 2 materials" in m for m in messages[0]), messages[0]
    assert any("nothing new to fit" in m for m in messages[1]), messages[1]
    report = json.loads((model / "report.json").read_text())
    assert report["incremental"]["fitted"] == [] and len(report["incremental"]["reused"]) == 2
    assert "nothing new to fit" in (model / "report.html").read_text()


def test_bad_deployment_files_and_no_server_are_named(tmp_path, monkeypatch, capsys):
    from flows.cli import main
    from flows.schedule import read_deployments

    shipped = read_deployments(REPO / "prefect.yaml")
    assert [e["name"] for e in shipped] == ["build-db", "ingest", "reconstruct", "evaluate-acquisition"]
    from prefect.flows import load_flow_from_entrypoint

    from flows.profiles import load_profile

    for entry in shipped:  # every parameter is one of its flow's, every profile loads
        entry_flow = load_flow_from_entrypoint(str(REPO / entry["entrypoint"]))
        assert set(entry["parameters"]) <= set(entry_flow.parameters.properties), entry["name"]
        load_profile(REPO / entry["parameters"]["cluster"])
    assert [s["cron"] for s in shipped[0]["schedules"]] == ["0 3 * * *"]
    bad = tmp_path / "prefect.yaml"
    cases = [
        ("deployments: {name: x}\n", "no 'deployments' list"),
        ("deployments: [{name: x}]\n", "deployment 'x': give its 'name' and 'entrypoint'"),
        ("deployments: [{name: x, entrypoint: flows/deploy.py:ingest, infra: y}]\n", "unknown key 'infra'"),
        ("deployments: [{name: x, entrypoint: a:b, schedules: [{cron: '0 3 * * *', interval: 5}]}]\n",
         "one of 'cron'"),
        ("deployments: [{name: x, entrypoint: a:b, work_pool: {name: p, image: i}}]\n", "work_pool: unknown key 'image'"),
    ]
    for text, message in cases:
        bad.write_text(text)
        with pytest.raises(ValueError, match=message):
            read_deployments(bad)
    with pytest.raises(ValueError, match="no deployment named nope; it has build-db"):
        read_deployments(REPO / "prefect.yaml", ["nope"])
    # no PREFECT_API_URL and no btf server: exit 3, saying how to get one
    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    assert main(["deploy"]) == 3
    assert "start one with `btf server start` or set PREFECT_API_URL" in capsys.readouterr().err
    bad.write_text(cases[2][0])
    assert main(["deploy", "--file", str(bad)]) == 2   # bad input is named before any API is asked


def test_a_deployment_runs_the_command_line():
    from flows.deploy import command_line

    assert command_line(["reconstruct", "m.zarr"], dict(model="M", material_class="cloth", out="o.zarr", lam=0.5,
                                                         k=None,
                                                         overwrite=True)) == [
        "reconstruct", "m.zarr", "--model", "M", "--class", "cloth", "--out", "o.zarr", "--lam", "0.5", "--overwrite"]
    assert command_line([], dict(device="tiny", materials_per_class=2, seed=None), prefix="eval-") == [
        "--eval-device", "tiny", "--eval-materials-per-class", "2"]


def test_schedule_serves_on_the_btf_server_when_no_api_is_set(monkeypatch, capsys, tmp_path):
    """`btf schedule build-db` without PREFECT_API_URL serves against the running btf server, with
    absolute paths (the served runs may start in another folder)."""
    import prefect

    import flows.schedule
    from flows.cli import main

    served = []
    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    monkeypatch.setattr(flows.schedule, "running_server", lambda: "http://127.0.0.1:9/api")
    monkeypatch.setattr(flows.schedule, "is_healthy", lambda url, timeout: True)
    monkeypatch.setattr(prefect, "serve", lambda *deployments: served.extend(deployments))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "db").mkdir()
    assert main(["schedule", "build-db", "db", "--out", "model", "--cron", "0 3 * * *"]) == 0
    assert os.environ.pop("PREFECT_API_URL") == "http://127.0.0.1:9/api"
    printed = json.loads(capsys.readouterr().out)
    assert printed["api"] == "http://127.0.0.1:9/api" and printed["serving"] == "btf-build-db-run/build-db"
    assert served[0].parameters["db"] == str(tmp_path / "db") and served[0].parameters["out"] == str(tmp_path / "model")
    assert [s.schedule.cron for s in served[0].schedules] == ["0 3 * * *"]
