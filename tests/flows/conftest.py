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


#: The tiny acquisition evaluation the flow tests share (about a minute on two cores).
TINY_EVALUATION = dict(device="tiny", n_turntable=None, texture_size=12, materials_per_class=2,
                       classes=("carpet", "stone", "leather"), sampling_steps=200, als_iterations=3,
                       band_rows=6, render_materials=1, render_size=32)


@pytest.fixture(scope="session")
def acquisition_evaluation(tmp_path_factory, runtime_session):
    """``(out, summary)`` of `btf evaluate acquisition`'s flow on a tiny truth database, run once:
    ``out`` is ``ROOT/acquisition`` with the truth database in ``ROOT/acquisition-database``, as a demo lays
    them out. What the run printed on stderr (not a terminal: a job log's progress lines) is in
    ``ROOT/stderr.log``."""
    import contextlib
    import io

    from flows.evaluate_acquisition import evaluate_acquisition_flow
    from tasks.evaluate_acquisition import EvaluationConfig

    root = tmp_path_factory.mktemp("demo-layout")
    with contextlib.redirect_stderr(io.StringIO()) as err:
        summary = evaluate_acquisition_flow(str(root / "acquisition-database"), str(root / "acquisition"),
                                            runtime_session[2].scheduler.address, EvaluationConfig(**TINY_EVALUATION),
                                            progress=True)
    (root / "stderr.log").write_text(err.getvalue())
    return root / "acquisition", summary


@pytest.fixture(scope="session")
def model_report(acquisition_evaluation, runtime_session):
    """``ROOT/model``: `btf build-db`'s flow (small bases) on the tiny evaluation's truth database, beside
    ``ROOT/acquisition``; holds ``report.html``."""
    from flows.model import build_db_flow
    from tasks.model import ModelSettings, with_k

    root = acquisition_evaluation[0].parent
    settings = with_k(ModelSettings(k_class=48, k_global=48, als_iterations=3), log_y=24, abtf_log_y=8, als=6)
    build_db_flow(str(root / "acquisition-database"), str(root / "model"), runtime_session[2].scheduler.address,
                  settings, progress=False)
    return root / "model"
