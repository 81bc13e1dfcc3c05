"""`btf ingest` and `btf build-db` on Dask workers that a real Slurm runs as jobs, and on workers of the
`address` kind (a `dask scheduler` and `dask worker` processes started here): the stores are bit-identical
to the local profile's, also when a worker job is cancelled mid-run (docs/clusters.md).

The Slurm tests need a Slurm controller that answers `sinfo` (CI starts a one-node one with
`infra/slurm/one-node.sh start`); elsewhere they are skipped with that reason. Select them with
`pytest -m slurm`. Every command reports to the session's Prefect server (PREFECT_API_URL), so that no
command pays for a temporary one.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from flows.profiles import DEFAULT_PROFILE

ROOT = DEFAULT_PROFILE.parents[1]


def _slurm_answers() -> bool:
    if shutil.which("sinfo") is None:
        return False
    try:
        out = subprocess.run(["sinfo", "-h", "-o", "%t"], capture_output=True, text=True, timeout=15)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return out.returncode == 0 and any(state.startswith(("idle", "mix", "alloc")) for state in out.stdout.split())


SLURM = _slurm_answers()
needs_slurm = pytest.mark.skipif(not SLURM, reason="no Slurm controller answers `sinfo` (start a one-node Slurm "
                                                   "as root: infra/slurm/one-node.sh install && ... start)")


def _same_files(a: Path, b: Path) -> None:
    """Every file of store ``a`` exists in ``b`` with the same bytes (chunks and zarr.json metadata)."""
    files = {p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file()}
    assert files == {p.relative_to(b).as_posix() for p in b.rglob("*") if p.is_file()}, (a, b)
    differ = [f for f in sorted(files) if (a / f).read_bytes() != (b / f).read_bytes()]
    assert differ == [], f"{b} differs from {a} in {differ[:5]}"


def _btf(prefect_url: str, *args: str) -> subprocess.CompletedProcess:
    """`btf ARGS` as its own process (as a user runs it; no logging state left in this one), reporting to
    the Prefect API ``prefect_url``; the finished process, its stdout the JSON summary."""
    run = subprocess.run([sys.executable, "-m", "flows.cli", "--no-progress", *args], cwd=ROOT, capture_output=True,
                         text=True, timeout=300, env={**os.environ, "PREFECT_API_URL": prefect_url})
    assert run.returncode == 0, run.stderr[-3000:]
    return run


def _slurm_profile(folder: Path, minimum_jobs: int = 1) -> Path:
    """infra/slurm.yaml with its job logs in ``folder`` (and ``minimum_jobs`` jobs kept)."""
    import yaml

    data = yaml.safe_load((ROOT / "infra" / "slurm.yaml").read_text())
    data["cluster"].update(log_directory=str(folder / "slurm-logs"), local_directory=str(folder / "spill"),
                           minimum_jobs=minimum_jobs)
    path = folder / f"slurm-{minimum_jobs}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def shared_prefect(runtime_session) -> str:
    """The session's Prefect API, which every command of this module reports to."""
    return runtime_session[1]


@pytest.fixture(scope="module")
def session_cluster(runtime_session, tmp_path_factory) -> Path:
    """A profile that reaches the session's cluster: the default (local) profile's LocalCluster, started by
    :func:`flows.runtime.runtime` with the worker environment. The reference stores are computed on it
    through the same `btf` commands, without starting a LocalCluster per command (seconds each on two
    loaded cores)."""
    path = tmp_path_factory.mktemp("session-profile") / "session.yaml"
    path.write_text(f"cluster: {{kind: address, address: '{runtime_session[2].scheduler.address}'}}\n")
    return path


@pytest.fixture(scope="module")
def local_run(tmp_path_factory, runtime_session, shared_prefect, session_cluster) -> Path:
    """Two tiny captures of one class (one turntable position), ingested and built into a model database by
    the local profile's workers: the reference every other kind must reproduce bit for bit."""
    from tasks.simulate import SimulationConfig, simulate_database

    root = tmp_path_factory.mktemp("profiles")
    config = SimulationConfig(device="tiny", n_materials=2, seed=3, classes=("stone",), n_turntable=1)
    for capture in simulate_database(config, root / "captures", runtime_session[2]).stores:
        _btf(shared_prefect, "--cluster", str(session_cluster), "ingest", capture,
             "--out", str(root / "local" / Path(capture).name))
    _btf(shared_prefect, "--cluster", str(session_cluster), "build-db", str(root / "local"),
         "--out", str(root / "local-model"))
    return root


@pytest.mark.slurm
@pytest.mark.slow
@needs_slurm
def test_ingest_and_build_db_on_slurm_workers_are_bit_identical_to_local(local_run, shared_prefect):
    """The bar: a Slurm run and a local run of `btf build-db` give bit-identical model stores."""
    profile = _slurm_profile(local_run)
    capture = sorted((local_run / "captures").glob("*.zarr"))[0]
    run = _btf(shared_prefect, "--cluster", str(profile), "ingest", str(capture),
               "--out", str(local_run / "slurm" / capture.name))
    assert "(slurm, " in run.stderr and "adaptive 1-2 jobs)" in run.stderr      # the ready line
    _same_files(local_run / "local" / capture.name, local_run / "slurm" / capture.name)
    report = json.loads((local_run / "slurm" / f"{capture.stem}.report.json").read_text())
    assert report["profile"]["path"] == str(profile) and report["profile"]["cluster"]["kind"] == "slurm"
    # the same database folder as the local build (the model records its stores' paths); its stores are
    # the ones the Slurm workers reproduce bit for bit (above)
    summary = json.loads(_btf(shared_prefect, "--cluster", str(profile), "build-db", str(local_run / "local"),
                              "--out", str(local_run / "slurm-model")).stdout)
    _same_files(local_run / "local-model" / "model.zarr", local_run / "slurm-model" / "model.zarr")
    assert json.loads(Path(summary["report_json"]).read_text())["profile"]["cluster"]["kind"] == "slurm"
    logs = list((local_run / "slurm-logs").glob("*.err"))
    assert logs, "the worker jobs wrote no log into log_directory"


def _written(store: Path) -> int:
    import zarr

    try:
        return int(zarr.open_group(str(store), mode="r")["written"][...].sum())
    except Exception:  # not created yet
        return 0


def _running_worker_jobs() -> list[str]:
    out = subprocess.run(["squeue", "-h", "-n", "btf-worker", "-t", "RUNNING", "-o", "%i"], capture_output=True,
                         text=True, timeout=15)
    return out.stdout.split()


@pytest.mark.slurm
@pytest.mark.slow
@needs_slurm
def test_a_worker_job_cancelled_mid_run_does_not_fail_the_run(local_run, shared_prefect, runtime_session,
                                                              session_cluster):
    """`scancel` of a running worker job while views remain: the run completes (Dask recomputes the lost
    worker's tasks on the other job or on the job adaptive scaling submits in its place) and the store is
    bit-identical to the local profile's. Mid-run is checked, not assumed: the store had some but not all
    views written when the job was cancelled, two worker jobs were running (so each had a task: more
    views were pending than workers), and the command was still running."""
    from tasks.simulate import SimulationConfig, simulate_database

    # all three turntable positions: 12 views, slow enough to cancel a job between the first and the last
    config = SimulationConfig(device="tiny", n_materials=1, seed=5, classes=("cloth",))
    capture = simulate_database(config, local_run / "captures-12", runtime_session[2]).stores[0]
    reference = local_run / "cancel-local.zarr"
    _btf(shared_prefect, "--cluster", str(session_cluster), "ingest", capture, "--out", str(reference))

    out = local_run / "cancel-slurm.zarr"
    env = {**os.environ, "PREFECT_API_URL": shared_prefect}
    proc = subprocess.Popen([sys.executable, "-m", "flows.cli", "--no-progress", "--cluster",
                             str(_slurm_profile(local_run, minimum_jobs=2)), "ingest", capture, "--out", str(out)],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    cancelled, written_then, jobs_then = None, None, []
    try:
        deadline = time.monotonic() + 150
        while proc.poll() is None and time.monotonic() < deadline:
            written = _written(out)
            jobs = _running_worker_jobs()
            if 0 < written and len(jobs) == 2:
                written_then, jobs_then, cancelled = written, jobs, jobs[0]
                subprocess.run(["scancel", cancelled], check=True, timeout=15)
                break
            time.sleep(0.05)
        assert cancelled is not None, "no point mid-run with two worker jobs was seen"
        assert proc.poll() is None, "the run had finished when the job was cancelled"
        stdout, stderr = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr[-3000:]
    assert 0 < written_then < 12, written_then
    assert cancelled not in _running_worker_jobs()
    assert json.loads(stdout)["stages"]["ingest"]["views_processed"] == 12
    _same_files(reference, out)


@pytest.mark.slow
def test_workers_of_the_address_kind_give_the_same_stores(local_run, shared_prefect, tmp_path):
    """A `dask scheduler` and two `dask worker` processes started here without the worker environment:
    btf connects to them, warns that they lack the memory settings, sets their thread counts, and
    gives the local profile's stores bit for bit."""
    dask_cli = str(Path(sys.executable).with_name("dask"))
    scheduler_file = tmp_path / "scheduler.json"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "PREFECT_API_URL"))}
    procs = [subprocess.Popen([dask_cli, "scheduler", "--host", "127.0.0.1", "--port", "0", "--dashboard-address",
                               "127.0.0.1:0", "--scheduler-file", str(scheduler_file)], cwd=ROOT, env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)]
    try:
        deadline = time.monotonic() + 60
        while not scheduler_file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        address = json.loads(scheduler_file.read_text())["address"]
        procs.append(subprocess.Popen([dask_cli, "worker", address, "--nworkers", "2", "--nthreads", "1",
                                       "--host", "127.0.0.1", "--no-dashboard"], cwd=ROOT, env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True))
        profile = tmp_path / "address.yaml"
        profile.write_text(f"cluster: {{kind: address, address: '{address}', timeout_s: 60}}\n")
        capture = sorted((local_run / "captures").glob("*.zarr"))[0]
        run = _btf(shared_prefect, "--cluster", str(profile), "ingest", str(capture),
                   "--out", str(tmp_path / capture.name))
        _same_files(local_run / "local" / capture.name, tmp_path / capture.name)
        assert f"the workers of {address} did not start with MALLOC_MMAP_THRESHOLD_=4194304" in run.stderr
        assert "(address, 2 workers" in run.stderr                      # the ready line: kind, worker count
        report = json.loads((tmp_path / f"{capture.stem}.report.json").read_text())
        assert report["profile"] == {"path": str(profile), "cluster": {"kind": "address", "address": address,
                                                                        "timeout_s": 60}}
        _btf(shared_prefect, "--cluster", str(profile), "build-db", str(local_run / "local"),
             "--out", str(tmp_path / "model"))
        _same_files(local_run / "local-model" / "model.zarr", tmp_path / "model" / "model.zarr")
    finally:
        for proc in reversed(procs):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
