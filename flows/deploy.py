"""The entry flows of the Prefect deployments in ``prefect.yaml``: one per ``btf`` command a work pool runs.

A deployment run is the command line run by a Prefect worker: each flow here takes the command's
arguments as plain parameters (paths as strings, numbers, flags; ``None`` leaves the command's own
default), turns them into the ``btf`` command line, and runs it as :func:`flows.cli.main` would: the
same parser, the same checks before anything starts (:func:`flows.cli._preflight`), the runtime of the
execution profile named by ``cluster`` (:func:`flows.runtime.runtime`: its Prefect API is the worker's,
``PREFECT_API_URL``, and its Dask cluster the profile's) and the command's own flow, which becomes a
subflow of this one. Bad input fails the run before any cluster starts, with the command line's message
as the run's error (docs/architecture.md, "Execution").

``btf deploy`` registers the deployments (:mod:`flows.schedule`); ``prefect worker start --pool NAME``
runs them. Relative paths are taken from the repository root, the working directory of every run.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

from prefect import flow

from flows.progress import say


def command_line(words: list[str], options: dict[str, Any], prefix: str = "") -> list[str]:
    """``btf`` arguments: ``words``, then ``--PREFIX-NAME VALUE`` for each option that is not ``None``
    (``True``: the flag alone; ``False``: left out; ``material_class``: ``--class``)."""
    argv = list(words)
    for name, value in options.items():
        if value is None or value is False:
            continue
        option = "--" + ("class" if name == "material_class" else prefix + name.replace("_", "-"))
        argv += [option] if value is True else [option, str(value)]
    return argv


def run_command(argv: list[str]) -> dict[str, Any]:
    """Run ``btf ARGV`` in this process as the command line does and return its JSON summary, with the
    execution profile used (``profile``) and the seconds the run took.

    Raises
    ------
    ValueError
        ``argv`` does not parse (the parser's message), or the command's checks refuse its inputs.
    flows.runtime.RuntimeUnavailable
        Prefect or the Dask cluster could not start.
    """
    from flows.cli import COMMANDS, _label, _preflight, build_parser, run_on_cluster

    usage = io.StringIO()
    try:
        with contextlib.redirect_stderr(usage):
            args = build_parser().parse_args(argv)
    except SystemExit:
        raise ValueError(f"btf {' '.join(argv)}: {usage.getvalue().strip().splitlines()[-1]}") from None
    command = COMMANDS[args.command]
    label = _label(args)
    prepared = _preflight(args, command)
    summary = {**run_on_cluster(args, command, prepared), "profile": prepared["profile"].path}
    say(f"{label}: done: {json.dumps(summary)}")
    return summary


@flow(name="btf-build-db-run", log_prints=False)
def build_db(db: str, out: str, cluster: str | None = None, classes: str | None = None,
             k_log_y: int | None = None, k_chroma: int | None = None, k_merged: int | None = None) -> dict[str, Any]:
    """``btf build-db DB --out OUT``: the model database of the ingested BTF stores in ``db``,
    incremental (a material whose bases are stored with the same inputs is not fitted again; the
    report's ``incremental`` entry says what was fitted).

    Parameters
    ----------
    db, out : str
        Folder of ingested BTF stores, one per material; output folder (``model.zarr``, reports).
    cluster : str, optional
        Execution profile (``infra/*.yaml``) [default: ``$BTF_CLUSTER_CONFIG`` or ``infra/local.yaml``].
    classes : str, optional
        JSON file of material classes for stores without one.
    k_log_y, k_chroma, k_merged : int, optional
        Basis sizes (paper 1 (den Brok et al.) §4.1) [default: the command's].
    """
    summary = run_command(command_line(["build-db", db], dict(out=out, cluster=cluster, classes=classes,
                                                             k_log_y=k_log_y, k_chroma=k_chroma, k_merged=k_merged)))
    incremental = json.loads(Path(summary["report_json"]).read_text()).get("incremental")
    if incremental:
        say(f"btf build-db: {incremental['summary']}")
    return {**summary, "incremental": incremental}


@flow(name="btf-ingest-run", log_prints=False)
def ingest(capture: str, out: str, cluster: str | None = None, white: str | None = None,
           white_albedo: float | None = None, colour_matrix: str | None = None,
           overwrite: bool = False) -> dict[str, Any]:
    """``btf ingest CAPTURE --out BTF``: a capture store (a capture folder's ``.zarr``) to a BTF store;
    an unfinished run resumes.

    Parameters
    ----------
    capture, out : str
        Capture store; BTF store to write.
    cluster : str, optional
        Execution profile (``infra/*.yaml``) [default: ``$BTF_CLUSTER_CONFIG`` or ``infra/local.yaml``].
    white, white_albedo, colour_matrix : optional
        Radiometric correction: white-standard BTF store, its albedo, colour-matrix JSON.
    overwrite : bool
        Replace a finished output of another run once the new one is complete.
    """
    return run_command(command_line(["ingest", capture], dict(out=out, cluster=cluster, white=white,
                                                              white_albedo=white_albedo, colour_matrix=colour_matrix,
                                                              overwrite=overwrite)))


@flow(name="btf-reconstruct-run", log_prints=False)
def reconstruct(measurement: str, model: str, material_class: str, out: str, cluster: str | None = None,
                basis: str | None = None, method: str | None = None, lam: float | None = None,
                k: int | None = None, white: str | None = None, white_albedo: float | None = None,
                colour_matrix: str | None = None, overwrite: bool = False) -> dict[str, Any]:
    """``btf reconstruct MEASUREMENT --model MODEL --class CLS --out BTF``: a full BTF from a measurement
    store and a class basis (paper 4, eq. (10) for multiplexed measurements).

    Parameters
    ----------
    measurement, model, material_class, out : str
        Measurement (or BTF) store; ``btf build-db`` folder; material class of the basis; BTF store to write.
    cluster : str, optional
        Execution profile (``infra/*.yaml``) [default: ``$BTF_CLUSTER_CONFIG`` or ``infra/local.yaml``].
    basis, method, lam, k : optional
        The solve: basis (als, log_y, abtf_log_y), method (pinv, tikhonov, direct, projection,
        thresholded), its lambda and the basis vectors used [default: the command's].
    white, white_albedo, colour_matrix : optional
        Radiometric correction, as for ``ingest``.
    overwrite : bool
        Replace another store at ``out`` once the new one is complete.
    """
    return run_command(command_line(["reconstruct", measurement], dict(
        model=model, material_class=material_class, out=out, cluster=cluster, basis=basis, method=method, lam=lam, k=k, white=white,
        white_albedo=white_albedo, colour_matrix=colour_matrix, overwrite=overwrite)))


@flow(name="btf-evaluate-acquisition-run", log_prints=False)
def evaluate_acquisition(db: str, out: str, cluster: str | None = None, device: str | None = None,
                         turntable: int | None = None, texture: int | None = None,
                         materials_per_class: int | None = None, seed: int | None = None,
                         render: int | None = None) -> dict[str, Any]:
    """``btf evaluate acquisition --db DB --out OUT``: leave-one-out evaluation of sparse, multiplexed
    and combined acquisition on a simulated truth database (docs/evaluation.md).

    Parameters
    ----------
    db, out : str
        Folder of truth BTF stores (missing ones are rendered into it); output folder.
    cluster : str, optional
        Execution profile (``infra/*.yaml``) [default: ``$BTF_CLUSTER_CONFIG`` or ``infra/local.yaml``].
    device, turntable, texture, materials_per_class, seed, render : optional
        The evaluation's scale (``--eval-*`` of the command) [default: the command's].
    """
    evaluation = dict(device=device, turntable=turntable, texture=texture, materials_per_class=materials_per_class,
                      seed=seed, render=render)
    argv = command_line(["evaluate", "acquisition"], dict(db=db, out=out, cluster=cluster))
    return run_command(argv + command_line([], evaluation, prefix="eval-"))
