"""Execution profiles, the shared Prefect server and the Dask cluster."""

from __future__ import annotations

import os

import pytest

from flows.runtime import DEFAULT_PROFILE, RuntimeUnavailable, dask_client, load_profile


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
    with pytest.raises(RuntimeUnavailable, match="does not exist"):
        load_profile(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("cluster: [unclosed\n")
    with pytest.raises(RuntimeUnavailable, match=r"bad\.yaml is not valid YAML"):
        load_profile(bad)
    slurm = tmp_path / "slurm.yaml"
    slurm.write_text("cluster: {kind: slurm}\n")
    with pytest.raises(RuntimeUnavailable, match=r"slurm\.yaml: cluster kind 'slurm' is not supported yet"):
        with dask_client(load_profile(slurm)):
            pass


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
