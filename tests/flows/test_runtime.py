"""Execution profiles, the shared Prefect server and the Dask cluster."""

from __future__ import annotations

import os

import pytest

from flows.runtime import DEFAULT_PROFILE, ProfileError, exposure_warnings, load_profile


def _worker_environ(keys):
    return {k: os.environ.get(k) for k in keys}


def test_workers_share_the_one_prefect_server(runtime_session):
    profile, url, client = runtime_session
    assert profile.path == str(DEFAULT_PROFILE)
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


def test_default_profile_is_a_two_worker_local_cluster():
    profile = load_profile(DEFAULT_PROFILE)
    assert profile.cluster["kind"] == "local"
    assert (profile.cluster["n_workers"], profile.cluster["threads_per_worker"]) == (2, 1)
    assert profile.prefect["api_url"] is None


def test_profile_errors_name_the_file(tmp_path):
    with pytest.raises(ProfileError, match="does not exist"):
        load_profile(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("cluster: [unclosed\n")
    with pytest.raises(ProfileError, match=r"bad\.yaml is not valid YAML"):
        load_profile(bad)
    slurm = tmp_path / "slurm.yaml"
    slurm.write_text("cluster: {kind: slurm}\n")
    # refused when loaded, before Prefect or a cluster starts (it used to be refused by dask_client)
    with pytest.raises(ProfileError, match=r"slurm\.yaml: cluster kind 'slurm' is not supported yet"):
        load_profile(slurm)
    assert issubclass(ProfileError, ValueError)  # the CLI's bad input


@pytest.mark.parametrize("text, message", [
    # a typo used to reach LocalCluster(**spec), after Prefect had started
    ("cluster: {kind: local, n_worker: 4}\n",
     "unknown key 'cluster.n_worker' for cluster kind 'local'; allowed keys: kind, n_workers, threads_per_worker, "
     "memory_limit, processes, dashboard, host, dashboard_address"),
    ("cluster: {kind: local, scheduler_kwargs: {dashboard: true}}\n", "unknown key 'cluster.scheduler_kwargs'"),
    ("prefect: {api_url: null, startup_timeout: 30}\n",
     "unknown key 'prefect.startup_timeout'; allowed keys: api_url, startup_timeout_s"),
    ("clusters: {kind: local}\n", "unknown section 'clusters'; allowed sections: cluster, prefect"),
    ("cluster: {n_workers: two}\n", "'cluster.n_workers' must be an integer, not 'two' (str)"),
    ("cluster: {n_workers: true}\n", "'cluster.n_workers' must be an integer, not True (bool)"),
    ("cluster: {n_workers: 0}\n", "'cluster.n_workers' must be at least 1, not 0"),
    ("cluster: {dashboard: 'yes please'}\n", "'cluster.dashboard' must be true or false"),
    ("cluster: {dashboard_address: 8787}\n", "'cluster.dashboard_address' must be a string, not 8787 (int)"),
    ("cluster: {memory_limit: 4 apples}\n", "'cluster.memory_limit' must be a size like 4GiB"),
    ("prefect: {startup_timeout_s: soon}\n", "'prefect.startup_timeout_s' must be a number, not 'soon' (str)"),
    ("prefect: {api_url: 8080}\n", "'prefect.api_url' must be a string or null"),
    ("cluster: [local]\n", "'cluster' must be a mapping of keys"),
    # safe_load refuses python tags; the message used to span four lines of PyYAML's marks
    ("cluster: !!python/object/apply:os.system ['touch pwned']\n",
     "is not valid YAML (line 1, column 10: could not determine a constructor for the tag "
     "'tag:yaml.org,2002:python/object/apply:os.system')"),
])
def test_a_profile_is_validated_against_its_cluster_kind_when_loaded(tmp_path, text, message):
    path = tmp_path / "profile.yaml"
    path.write_text(text)
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    assert str(info.value).startswith(f"execution profile {path}")
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_only_a_profile_that_binds_beyond_loopback_without_tls_is_warned(tmp_path):
    import dask

    def profile(text):
        path = tmp_path / "p.yaml"
        path.write_text(text)
        return load_profile(path)

    assert exposure_warnings(load_profile(DEFAULT_PROFILE)) == []
    assert exposure_warnings(profile("cluster: {dashboard: true}\n")) == []      # 127.0.0.1:8787
    assert exposure_warnings(profile("cluster: {host: localhost, dashboard_address: '[::1]:8787'}\n")) == []
    public = profile("cluster: {host: 0.0.0.0, dashboard: true}\n")
    lines = exposure_warnings(public)
    assert len(lines) == 2 and all("\n" not in line and str(public.path) in line for line in lines)
    assert "scheduler and workers listen on 0.0.0.0 (cluster.host) without TLS" in lines[0]
    assert "HTTP server" in lines[1] and "0.0.0.0:8787" in lines[1]
    dashboard = exposure_warnings(profile("cluster: {dashboard: true, dashboard_address: ':8787'}\n"))
    assert len(dashboard) == 1 and "listens on :8787 without TLS" in dashboard[0]
    with dask.config.set({"distributed.comm.require-encryption": True,
                          "distributed.scheduler.dashboard.tls.cert": "cert.pem"}):
        assert exposure_warnings(public) == []
    assert len(exposure_warnings(profile("cluster: {host: 'tls://0.0.0.0'}\n"))) == 1   # its HTTP server has no TLS


def test_a_failed_run_prints_no_prefect_traceback_unless_asked(runtime_session, monkeypatch, capfd):
    """Prefect logged a failed task and flow run with their tracebacks before the CLI's one-line message."""
    from prefect import flow, task

    from flows.runtime import quiet_logs

    monkeypatch.setenv("PREFECT_API_URL", runtime_session[1])
    monkeypatch.delenv("PREFECT_LOGGING_LEVEL", raising=False)
    quiet_logs()                                           # as a `btf` run starts: the user set no level

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
import dataclasses, json, sys, time
from urllib.parse import urlsplit
import psutil
from flows.runtime import DEFAULT_PROFILE, load_profile, runtime

def listening():
    me = psutil.Process()
    return [[proc.pid, conn.laddr.ip, conn.laddr.port]
            for proc in [me, *me.children(recursive=True)]
            for conn in proc.net_connections(kind="inet") if conn.status == psutil.CONN_LISTEN]

if __name__ == "__main__":
    default = load_profile(DEFAULT_PROFILE)          # the default profile, on one worker to save time
    profile = dataclasses.replace(default, cluster={**default.cluster, "n_workers": 1})
    with runtime(profile) as (_p, url, client):
        sockets = listening()
        busy = client.submit(time.sleep, 60, pure=False)     # still running when the run ends
        deadline = time.monotonic() + 30
        while not any(client.processing().values()) and time.monotonic() < deadline:
            time.sleep(0.1)
    print(json.dumps({"prefect_port": urlsplit(url).port, "sockets": sockets}))
"""


def test_a_default_run_listens_on_loopback_only_and_ends_quietly(tmp_path):
    """Every listening socket of a default run (temporary Prefect server, scheduler and its HTTP server,
    nanny, worker) binds the loopback: the scheduler's HTTP server (/metrics, worker addresses, logs)
    used to listen on 0.0.0.0 even without the dashboard. And the run ends without Dask's shutdown
    warnings: a worker still busy when the run ends used to print "Worker process still alive after
    4.0 seconds, killing"."""
    import json
    import subprocess
    import sys

    script = tmp_path / "listening.py"
    script.write_text(_LISTENING_RUN)
    root = DEFAULT_PROFILE.parents[1]
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "BTF_CLUSTER_CONFIG")}
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


def test_a_finished_run_leaves_the_environment_as_it_was(tmp_path):
    """distributed applies the workers' environment to this process too; the runtime undoes it,
    so that a second run in the same process does not inherit the first one's Prefect URL."""
    import subprocess
    import sys

    code = (
        "import os\n"
        "from flows.runtime import runtime\n"
        "if __name__ == '__main__':\n"
        "    before = {k: os.environ.get(k) for k in ('PREFECT_API_URL', 'OMP_NUM_THREADS')}\n"
        "    for _ in range(2):\n"
        "        with runtime() as (_p, url, client):\n"
        "            assert client.run(lambda: os.environ['PREFECT_API_URL'])\n"
        "    after = {k: os.environ.get(k) for k in before}\n"
        "    print(before == after)\n"
    )
    script = tmp_path / "twice.py"
    script.write_text(code)
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "OMP_NUM_THREADS")}
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=240, env=env,
                         cwd=str(tmp_path))
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().endswith("True")
