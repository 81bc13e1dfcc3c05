"""tasks.faults: a process kills itself at the named point and occurrence, and only there."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: Passes the point ``x`` three times, then ``y`` once, then says it is alive.
SCRIPT = "from tasks.faults import kill_point\nfor p in 'xxxy': kill_point(p)\nprint('alive')"


def _run(**environ: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("BTF_KILL")}
    return subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, capture_output=True, text=True, timeout=60,
                          env={**env, **environ})


def test_kills_at_the_named_occurrence_only():
    assert _run().stdout == "alive\n"
    assert _run(BTF_KILL_AT="x:4").stdout == "alive\n"           # only three
    assert _run(BTF_KILL_AT="z").stdout == "alive\n"             # a point never passed
    killed = _run(BTF_KILL_AT="x:2")
    assert killed.returncode == -signal.SIGKILL and killed.stdout == ""
    assert killed.stderr == f"btf: BTF_KILL_AT=x:2: process {killed.stderr.split()[3]} killed at x (occurrence 2)\n"
    assert _run(BTF_KILL_AT="y").returncode == -signal.SIGKILL


def test_the_worker_kill_is_never_the_driver(tmp_path):
    # outside a Dask worker's task the once-only worker kill does nothing, and creates no sentinel
    sentinel = tmp_path / "sentinel"
    script = "from tasks.faults import kill_point\nkill_point('chunk-written')\nprint('alive')"
    env = {k: v for k, v in os.environ.items() if not k.startswith("BTF_KILL")}
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=60,
                          env={**env, "BTF_KILL_WORKER_ONCE": str(sentinel)})
    assert done.stdout == "alive\n" and not sentinel.exists()


def test_a_worker_kills_itself_once_and_the_task_is_retried(dask_client, tmp_path):
    from tasks.faults import kill_point

    sentinel = tmp_path / "sentinel"
    n_workers = len(dask_client.scheduler_info()["workers"])

    def chunk(i: int) -> int:
        kill_point("chunk-written")
        return i * i

    def arm(value: str | None) -> None:
        if value is None:
            os.environ.pop("BTF_KILL_WORKER_ONCE", None)
        else:
            os.environ["BTF_KILL_WORKER_ONCE"] = value

    dask_client.run(arm, f"{sentinel}:2")                       # the second chunk of a worker
    try:
        futures = [dask_client.submit(chunk, i, pure=False) for i in range(6)]
        assert dask_client.gather(futures) == [i * i for i in range(6)]
    finally:
        dask_client.run(arm, None)
    pid, point, occurrence = sentinel.read_text().split()
    assert point == "chunk-written" and occurrence == "2"
    dask_client.wait_for_workers(n_workers, timeout=120)
    assert int(pid) not in dask_client.run(os.getpid).values()     # that worker process is gone, replaced
