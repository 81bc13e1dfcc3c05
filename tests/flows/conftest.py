"""Fixtures of the flow tests."""

from __future__ import annotations

import pytest


@pytest.fixture()
def run_btf(runtime_session, tmp_path_factory, monkeypatch, capsys):
    """``run_btf(*args, progress=False) -> (exit code, stdout, stderr)``: the real ``btf`` command line
    (``flows.cli.main``) in this process, on the session's Prefect server and a one-worker
    threaded LocalCluster, so that a command costs about a second instead of a server start."""
    from flows.cli import main

    profile = tmp_path_factory.getbasetemp() / "in-process-cluster.yaml"
    profile.write_text("cluster: {kind: local, n_workers: 1, threads_per_worker: 1, processes: false}\n")
    monkeypatch.setenv("PREFECT_API_URL", runtime_session[1])

    def run(*args, progress: bool = False) -> tuple[int, str, str]:
        capsys.readouterr()
        code = main(["--cluster", str(profile), *([] if progress else ["--no-progress"]), *map(str, args)])
        captured = capsys.readouterr()
        return code, captured.out, captured.err

    return run
