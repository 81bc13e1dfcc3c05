"""Execution profiles, the shared Prefect server and the Dask cluster."""

from __future__ import annotations

import os

import pytest

from flows.runtime import DEFAULT_PROFILE


def _worker_environ(keys):
    return {k: os.environ.get(k) for k in keys}


def test_workers_share_the_one_prefect_server(runtime_session):
    profile, url, client = runtime_session
    assert profile.path == str(DEFAULT_PROFILE)
    client.wait_for_workers(2, timeout=60)       # a worker an earlier test killed may be restarting
    info = client.scheduler_info()
    assert len(info["workers"]) == 2
    assert all(w["nthreads"] == 1 for w in info["workers"].values())
    environ = client.run(_worker_environ, ["PREFECT_API_URL", "OMP_NUM_THREADS", "NUMPY_MADVISE_HUGEPAGE"])
    assert len(environ) == 2
    for env in environ.values():
        assert env == {"PREFECT_API_URL": url, "OMP_NUM_THREADS": "1", "NUMPY_MADVISE_HUGEPAGE": "0"}


def _worker_setup() -> tuple[int, bool]:
    import sys

    import cv2

    return cv2.getNumThreads(), "tasks.ingest" in sys.modules


def test_workers_pin_opencv_to_one_thread_and_start_with_the_pipeline_imported(runtime_session):
    client = runtime_session[2]
    assert set(client.run(_worker_setup).values()) == {(1, True)}
    client.restart()                                 # a restarted worker gets the same setup
    assert set(client.run(_worker_setup).values()) == {(1, True)}


def test_a_failed_run_prints_no_prefect_traceback_unless_asked(runtime_session, monkeypatch, capfd):
    """Prefect logged a failed task and flow run with their tracebacks before the CLI's one-line message."""
    from prefect import flow, task

    from flows.runtime import quiet_logs

    monkeypatch.setenv("PREFECT_API_URL", runtime_session[1])
    monkeypatch.delenv("PREFECT_LOGGING_LEVEL", raising=False)
    quiet_logs()                                           # as a `btf` run starts: the user set no level
    # Prefect's console handler keeps the stream it was configured with; when an earlier test configured
    # it, that is pytest's global capture (or a closed capfd file), which this test's capfd does not see
    import logging
    import sys

    from prefect.logging.handlers import PrefectConsoleHandler
    for handler in logging.getLogger().handlers + logging.getLogger("prefect").handlers:
        if isinstance(handler, PrefectConsoleHandler):
            monkeypatch.setattr(handler, "stream", sys.stderr)
            monkeypatch.setattr(handler.console, "file", sys.stderr)   # it prints through a rich Console

    @task(name="bad-input-stage")
    def stage():
        raise ValueError("capture.zarr: exposure_time[3] is negative")

    @flow(name="bad-input-flow")
    def run():
        stage()

    capfd.readouterr()
    with pytest.raises(ValueError, match="negative"):
        run()
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Finished in state Failed" not in err, err
    monkeypatch.setenv("PREFECT_LOGGING_LEVEL", "INFO")    # asked for: Prefect's report is kept
    with pytest.raises(ValueError, match="negative"):
        run()
    assert "Traceback" in capfd.readouterr().err


_LISTENING_RUN = """
import dataclasses, json, os, sys, time
from urllib.parse import urlsplit
import psutil
from flows.runtime import DEFAULT_PROFILE, load_profile, runtime

def listening():
    me = psutil.Process()
    return [[proc.pid, conn.laddr.ip, conn.laddr.port]
            for proc in [me, *me.children(recursive=True)]
            for conn in proc.net_connections(kind="inet") if conn.status == psutil.CONN_LISTEN]

if __name__ == "__main__":
    before = {k: os.environ.get(k) for k in ("PREFECT_API_URL", "OMP_NUM_THREADS")}
    default = load_profile(DEFAULT_PROFILE)          # the default profile, on one worker to save time
    profile = dataclasses.replace(default, cluster={**default.cluster, "n_workers": 1})
    with runtime(profile) as (_p, url, client):
        sockets = listening()
        busy = client.submit(time.sleep, 60, pure=False)     # still running when the run ends
        deadline = time.monotonic() + 30
        while not any(client.processing().values()) and time.monotonic() < deadline:
            time.sleep(0.1)
    with runtime(profile) as (_p, second_url, client):      # a second run in the same process
        worker_urls = sorted(set(client.run(lambda: os.environ["PREFECT_API_URL"]).values()))
    after = {k: os.environ.get(k) for k in before}
    print(json.dumps({"prefect_port": urlsplit(url).port, "sockets": sockets, "second_url": second_url,
                      "second_worker_urls": worker_urls, "environment_restored": before == after}))
"""


def test_a_default_run_listens_on_loopback_only_ends_quietly_and_leaves_the_environment(tmp_path):
    """Every listening socket of a default run (temporary Prefect server, scheduler and its HTTP server,
    nanny, worker) binds the loopback: the scheduler's HTTP server (/metrics, worker addresses, logs)
    used to listen on 0.0.0.0 even without the dashboard. The run ends without Dask's shutdown
    warnings: a worker still busy when the run ends used to print "Worker process still alive after
    4.0 seconds, killing". And distributed applies the workers' environment to this process too; the
    runtime undoes it, so that a second run in the same process does not inherit the first one's Prefect
    URL (both checked in one process: each run starts a Prefect server and a cluster)."""
    import json
    import subprocess
    import sys

    script = tmp_path / "listening.py"
    script.write_text(_LISTENING_RUN)
    root = DEFAULT_PROFILE.parents[1]
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "BTF_CLUSTER_CONFIG", "OMP_NUM_THREADS")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(root), env.get("PYTHONPATH")]))
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=240, env=env,
                         cwd=str(tmp_path))
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    sockets = report["sockets"]
    assert len({pid for pid, _, _ in sockets}) == 3, sockets     # this process, the Prefect server, a worker
    assert report["prefect_port"] in {port for _, _, port in sockets}
    assert len(sockets) >= 6, sockets        # Prefect, scheduler, its HTTP server, nanny, worker, worker HTTP
    exposed = [s for s in sockets if s[1] not in ("127.0.0.1", "::1")]
    assert exposed == [], f"listening beyond loopback: {exposed}"
    assert "still alive" not in out.stderr and "Traceback" not in out.stderr, out.stderr[-3000:]
    assert "WARNING" not in out.stderr, out.stderr[-3000:]
    assert report["second_worker_urls"] == [report["second_url"]] and report["environment_restored"], report


_CLOSE_DURING_HEARTBEATS = """
import sys
import time

import distributed.scheduler

from flows import runtime

if __name__ == "__main__":
    distributed.scheduler.heartbeat_interval = lambda n_workers: 0.0005   # the workers heartbeat all the time
    runtime.quiet_logs()
    from distributed import Client

    cluster = runtime._local_cluster({"n_workers": 2, "threads_per_worker": 1, "memory_limit": "1GiB"}, {})
    client = Client(cluster)
    busy = [client.submit(time.sleep, 3, pure=False) for _ in range(2)]   # a failed run's tasks still running
    time.sleep(1.0)
    runtime._close_quietly(client, cluster)
    print("closed", file=sys.stderr)
"""


def test_closing_while_workers_heartbeat_prints_no_traceback(tmp_path):
    """A worker whose heartbeat meets the closing scheduler's connection logs "Failed to communicate with
    scheduler during heartbeat" at ERROR, with a traceback, in front of ``btf``'s one-line message (seen
    in CI on a full disk's failed run). With the workers heartbeating every 0.5 ms the race is hit in
    most closes: 5 of 6 with the close's level at ERROR, as it was."""
    import subprocess
    import sys

    script = tmp_path / "close.py"
    script.write_text(_CLOSE_DURING_HEARTBEATS)
    root = DEFAULT_PROFILE.parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    env.pop("DASK_LOGGING__DISTRIBUTED", None)
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, env=env,
                         cwd=str(tmp_path))
    assert out.returncode == 0 and out.stderr.strip() == "closed", out.stderr[-3000:]


def _blas_threads() -> set[int]:
    from threadpoolctl import threadpool_info

    return {pool["num_threads"] for pool in threadpool_info()}


def test_worker_setup_pins_blas_to_one_thread(runtime_session):
    assert set().union(*runtime_session[2].run(_blas_threads).values()) == {1}


def test_a_slurm_job_script_exports_the_worker_environment_before_the_worker_starts(tmp_path):
    """The worker environment reaches Slurm workers through the job script (no Slurm needed to check it)."""
    from flows.clusters import jobqueue_options
    from flows.profiles import load_profile
    from flows.runtime import worker_environ

    profile = tmp_path / "slurm.yaml"
    profile.write_text("cluster: {kind: slurm, cores: 2, memory: 3GiB, processes: 2, walltime: '02:00:00', "
                       "queue: short, account: btf-lab, job_extra_directives: ['--qos=low'], interface: lo, "
                       "job_script_prologue: ['module load python/3.11'], log_directory: logs}\n")
    spec = load_profile(profile).cluster
    environ = worker_environ("http://127.0.0.1:4200/api")
    cls, options = jobqueue_options(spec, environ)
    assert cls.__name__ == "SLURMCluster" and options["scheduler_options"]["dashboard_address"] == "127.0.0.1:0"
    cluster_only = ("scheduler_options", "silence_logs")
    script = cls.job_cls(scheduler="tcp://127.0.0.1:8786",
                         **{k: v for k, v in options.items() if k not in cluster_only}).job_script()
    for line in ("#SBATCH -p short", "#SBATCH -A btf-lab", "#SBATCH -t 02:00:00", "#SBATCH --qos=low",
                 f"#SBATCH -e {tmp_path / 'logs'}/", "#SBATCH --cpus-per-task=2", "#SBATCH -J btf-worker",
                 "export MALLOC_MMAP_THRESHOLD_=4194304", "export OMP_NUM_THREADS=1",
                 "export PREFECT_API_URL=http://127.0.0.1:4200/api"):
        assert line in script, (line, script)
    lines = script.splitlines()
    start = next(i for i, line in enumerate(lines) if "distributed.cli.dask_worker" in line)
    prologue = lines.index("module load python/3.11")
    assert prologue < lines.index("export OMP_NUM_THREADS=1") < start      # after the user's lines, before the worker
    assert "--nthreads 1 " in lines[start] and "--nworkers 2 " in lines[start] and "--interface lo" in lines[start]


def _address_profile(tmp_path, client, timeout_s: float):
    from flows.profiles import load_profile

    path = tmp_path / "address.yaml"
    path.write_text(f"cluster: {{kind: address, address: '{client.scheduler.address}', timeout_s: {timeout_s}}}\n")
    return load_profile(path)


def test_connecting_to_a_scheduler_retries_when_a_worker_leaves_during_the_setup(runtime_session, tmp_path,
                                                                                   monkeypatch):
    """A worker that leaves while ``btf`` sets the workers up (the scheduler's broadcast meets its closed
    connection: seen in the kill matrix right after a worker was replaced) used to fail the run at once with
    "has no usable worker"; it is tried again within the profile's timeout. The leaving worker is injected
    (CommClosedError on the first broadcast): the race itself cannot be caused on demand."""
    from distributed import Client
    from distributed.comm.core import CommClosedError

    from flows.runtime import RuntimeUnavailable, _connect, worker_environ

    _, url, client = runtime_session
    original, calls = Client.register_plugin, []

    def leaving_once(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise CommClosedError("in <TCP (closed) Scheduler Broadcast>: Stream is closed")
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Client, "register_plugin", leaving_once)
    connected = _connect(_address_profile(tmp_path, client, 20), worker_environ(url))
    try:
        assert len(calls) == 2 and len(connected.scheduler_info()["workers"]) >= 1
    finally:
        connected.close()

    def always(self, *args, **kwargs):
        raise CommClosedError("in <TCP (closed) Scheduler Broadcast>: Stream is closed")

    monkeypatch.setattr(Client, "register_plugin", always)
    with pytest.raises(RuntimeUnavailable, match=r"has no usable worker within 3 s: .*Stream is closed"):
        _connect(_address_profile(tmp_path, client, 3), worker_environ(url))
