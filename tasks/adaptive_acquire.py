"""``btf acquire --adaptive``: the loop on one material, resumable through its step journal.

The loop, its executors, plans and report are :mod:`tasks.adaptive`'s; this module runs them for one
material (the simulator on a truth BTF store, or a dome's shots through plan files, ``--measured``) and
keeps the **step journal** (``journal.json``, :func:`open_journal`): every finished step, keyed by the
run's inputs, so that a killed run resumes where it stopped (docs/adaptive-capture.md, "Resume").
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from btfcore.acquisition.noise import SensorNoise
from btfcore.acquisition.strategies import Geometry
from btfcore.dome import Device
from tasks.adaptive import (ADAPTIVE_VERSION, AwaitingShot, adaptive_material, adaptive_plan, committee_bases,
                            measured_executor, step_measurement, write_adaptive_report)
from tasks.stores.common import json_key

__all__ = ["ACQUIRE_OUTPUTS", "JOURNAL", "acquire_adaptive", "open_journal"]

#: The step journal of ``btf acquire --adaptive`` in its output folder (:func:`open_journal`).
JOURNAL = "journal.json"
#: What ``btf acquire --adaptive`` writes in its output folder besides the journal.
ACQUIRE_OUTPUTS = ("plans", "plan.json", "plan.csv", "report.json", "report.html", "error_vs_shots.png")
#: Relative tolerance of a replayed step's recomputed errors against its journal entry.
REPLAY_RTOL = 1e-6


def _array_digest(*arrays: np.ndarray) -> str:
    digest = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        digest.update(f"{a.dtype.str}{a.shape}".encode())
        digest.update(a.tobytes())
    return digest.hexdigest()[:16]


def open_journal(out: Path, key: str, inputs: dict[str, Any], overwrite: bool = False) -> dict[str, Any]:
    """The step journal ``OUT/journal.json`` of the run ``key``: the one on disk, or a new one.

    The journal (written atomically after every step, :func:`tasks.report.write_json`) holds
    ``{"schema", "version", "key", "inputs", "steps": [step records], "finished"}``. One of another key,
    an unreadable one, or outputs without a journal are refused unless ``overwrite``, which deletes the
    journal and the outputs of :data:`ACQUIRE_OUTPUTS` (nothing else in ``out``) and starts a new one.
    The new journal is returned, not yet written.

    Raises
    ------
    ValueError
        ``out`` holds another run's steps or outputs and ``overwrite`` is false; the message names
        the inputs that differ and the option.
    """
    path = out / JOURNAL
    journal = None
    if path.exists():
        try:
            journal = json.loads(path.read_text())
        except (OSError, ValueError):
            journal = {}
        journal = journal if isinstance(journal, dict) else {}
        if journal.get("key") == key and journal.get("schema") == "btf-adaptive-journal":
            return journal
    found = [name for name in ACQUIRE_OUTPUTS if (out / name).exists()]
    if journal is not None or found:
        if not overwrite:
            if journal:
                old = journal.get("inputs") or {}
                differ = sorted(k for k in {*old, *inputs} if old.get(k) != inputs.get(k)) or ["version"]
                why = f"holds the step journal of a run of other inputs ({', '.join(differ)} differ)"
            elif journal is not None:
                why = f"holds an unreadable step journal {JOURNAL}"
            else:
                why = f"holds the outputs of a run without a step journal ({', '.join(found)})"
            raise ValueError(f"--out {out} {why}; give --overwrite to discard them and start over, or another "
                             "--out (the same inputs resume the run)")
        path.unlink(missing_ok=True)
        for name in found:
            if (out / name).is_dir():
                shutil.rmtree(out / name)
            else:
                (out / name).unlink()
    return {"schema": "btf-adaptive-journal", "version": ADAPTIVE_VERSION, "key": key, "inputs": inputs,
            "steps": [], "finished": False}


def _check_replayed(step: dict[str, Any], recorded: dict[str, Any], journal: Path) -> None:
    """A replayed step, recomputed, must be its journal entry (CPU seconds aside): else the inputs changed."""
    for name, value in recorded.items():
        new = step.get(name)
        same = (name == "cpu_s" or new == value or (isinstance(value, float) and isinstance(new, float)
                                                    and bool(np.isclose(new, value, rtol=REPLAY_RTOL, atol=0))))
        if not same:
            raise ValueError(f"{journal}: step {recorded.get('step')} recorded {name} = {value!r}, its replay gives "
                             f"{new!r}: the inputs changed although their key did not; give --overwrite to start "
                             "over")


@dataclass
class _Loop:
    """What :func:`acquire_adaptive` runs the loop with (:func:`_loop_setup`)."""

    U: np.ndarray
    sigma: np.ndarray
    geometry: Geometry
    device: Device
    noise: SensorNoise
    truth: np.ndarray | None
    truth_store: Any
    measure: Any
    source: dict[str, Any]
    where: Any
    attrs: dict[str, Any]
    texture_shape: tuple[int, int]
    material: str
    committee: list[tuple[np.ndarray, np.ndarray]]


def _loop_setup(truth_path: Any, measured: Any, model_path: Any, cls: str, device_name: str | None,
                calibration: Any, select: str) -> _Loop:
    """The basis, geometry, device, noise, executor and committee of a ``btf acquire`` run: the simulator on
    ``truth_path`` or a dome's shots in ``measured`` (:func:`measured_executor`); with ``select='committee'``
    every per-material ALS basis of the model store but the simulated material's own (:func:`committee_bases`);
    every input checked, named in the errors."""
    from btfcore.dome import get_device
    from tasks.reconstruct import RowCorrection, class_basis, check_sampling, open_model
    from tasks.stores.btf import open_btf_store
    from tasks.stores.measurement import open_measurement_store

    model = open_model(model_path)
    U, sigma = class_basis(model, cls, "als", None, model_path)
    if measured is None:
        truth_store = open_btf_store(truth_path, produced_by="`btf evaluate acquisition` (its truth database)")
        attrs = dict(truth_store.attrs)
        n_lv, h, w, _ = truth_store.btf.shape
        tcl = attrs.get("turntable_cameras_leds")
        device_name = device_name or (attrs.get("evaluation") or {}).get("device")
        where = truth_path
    else:
        truth_store, attrs, where = None, {}, measured
        first = step_measurement(measured, 0)
        first_store = open_measurement_store(first) if first.exists() else None
        h, w = (1, 1) if first_store is None else first_store["measured"].shape[1:3]
        n_lv, tcl = U.shape[0], None
    device = get_device(device_name) if device_name else None
    if tcl is None and device is not None:
        tcl = [n_lv // (device.n_cam * device.n_leds), device.n_cam, device.n_leds]
    if tcl is None or int(np.prod(tcl)) != n_lv:
        raise ValueError(f"{where}: its {n_lv} rows are not (turntable, camera, LED) of a known layout "
                         f"(turntable_cameras_leds {tcl!r}); give --device of the dome that wrote it")
    geometry = Geometry(int(tcl[0]), int(tcl[1]), int(tcl[2]), h, w)
    if device is None:
        raise ValueError(f"{where}: no device recorded; give --device (the plans are written for it)")
    if (device.n_cam, device.n_leds) != (geometry.n_cam, geometry.n_leds) or device.n_turn < geometry.n_turn:
        raise ValueError(f"--device {device.name}: {device.n_turn} x {device.n_cam} x {device.n_leds} does not hold "
                         f"the {geometry.n_turn} x {geometry.n_cam} x {geometry.n_leds} rows of {where}")
    device = device.with_overrides(turntable_angle_deg=device.turntable_angle_deg[:geometry.n_turn])
    noise = SensorNoise(float(device.sensor.full_well_e), float(device.sensor.read_noise_e))
    if measured is None:
        check_sampling(model, truth_store.group, truth_path)
        truth, measure = np.asarray(truth_store.btf[...], dtype=np.float32), None
        source = {"truth": truth_store.content_key or _array_digest(truth)}
    else:
        if first_store is not None:
            check_sampling(model, first_store, first)
        truth = None
        correction = None if calibration is None else \
            RowCorrection.of(calibration.led_gain, calibration.colour_matrix, None, n_lv)
        measure = measured_executor(Path(measured), noise, correction)
        source = {"measured": str(Path(measured).resolve()),
                  **({"calibration": calibration.key()} if calibration is not None else {})}
    material = (attrs.get("material") or {}).get("material_id") or Path(str(where)).stem
    committee = committee_bases(model, exclude=material) if select == "committee" else []
    if select == "committee" and not committee:
        raise ValueError(f"{model_path}: no per-material ALS basis (materials/<id>/als) besides {material}'s for "
                         "the committee; build the model with `btf build-db`, or choose --select posterior")
    return _Loop(U, sigma, geometry, device, noise, truth, truth_store, measure, source, where, attrs, (h, w),
                 material, committee)


def _journal_inputs(loop: _Loop, cls: str, simulated: bool, settings: dict[str, Any]) -> dict[str, Any]:
    """What a run's steps depend on (its journal's key): the truth or the dome's shots, the basis and the
    committee (digests), class, device, geometry and the loop's ``settings``; not the paths."""
    g = loop.geometry
    return {"version": ADAPTIVE_VERSION, **loop.source, "basis": _array_digest(loop.U, loop.sigma), "class": cls,
            "device": loop.device.name,
            "geometry": [g.n_turn, g.n_cam, g.n_leds, *(list(loop.texture_shape) if simulated else [])],
            "committee": _array_digest(*(a for pair in loop.committee for a in pair)), **settings}


def acquire_adaptive(truth_path: str | os.PathLike, model_path: str | os.PathLike, cls: str,
                     out_dir: str | os.PathLike, *, target: float, budget: int | None = None,
                     device_name: str | None = None, seed: int = 0, compare: bool = True,
                     sampling_steps: int = 1500, predictor: str = "posterior", weighting: str = "relative",
                     overwrite: bool = False, say: Callable[[str], None] | None = None,
                     time_aware: bool = False, measured: str | os.PathLike | None = None,
                     calibration: Any = None, select: str = "committee",
                     measured_rows: str = "fused") -> dict[str, Any]:
    """``btf acquire --adaptive`` on a simulated material: the loop on a truth BTF store, plans, report.

    Resumable (docs/adaptive-capture.md, "Resume"): every finished step is recorded in the journal
    ``OUT/journal.json`` (:func:`open_journal`), keyed by the inputs (:func:`_journal_inputs`); a rerun
    with the same inputs replays the recorded steps (measures their groups again, chooses nothing) and
    continues, and its outputs equal an uninterrupted run's; a finished run's rerun only reads its report.

    Parameters
    ----------
    truth_path : path
        A noise-free ``btf-texture`` store (e.g. of ``btf evaluate acquisition``'s truth database), rows
        ``(turntable, camera, light)``; its ``turntable_cameras_leds`` (or ``device_name``) gives the groups.
    model_path : path
        ``btf build-db``'s output; the class ``cls``'s ALS basis (paper 4) is used.
    out_dir : path
        ``report.json``, ``report.html``, ``plans/step_NNN.json`` (one shot each), ``plan.json`` (all
        shots in acquisition order, with the predicted time), ``journal.json`` (the finished steps).
    target : float
        Stop when the predicted relative L2 error of log Y is at most this (a fraction).
    budget : int, optional
        Most shots (default: every (turntable, LED) group).
    overwrite : bool
        Discard the steps and outputs of a run of other inputs at ``out_dir`` (else refused).
    time_aware : bool
        Choose by expected reduction per second of the time model, a turntable move included
        (:func:`adaptive_material`), instead of per shot.
    measured : path, optional
        A real dome's loop instead of the simulator (``truth_path`` None): step ``k``'s shot is read from
        ``MEASURED/step_kkk.zarr`` (:func:`measured_executor`), ``btf ingest`` of the capture of
        ``OUT/plans/step_kkk.json``. Where it is missing the run writes that plan and returns
        ``{"waiting": {...}}``; the next run replays the recorded steps from their stores and goes on.
        No true error, no fixed samplings. ``device_name`` is required.
    calibration : tasks.radiometric.Calibration, optional
        With ``measured``: the white standard's LED gains and the colour matrix the rows are corrected by.
    select, measured_rows : str
        The choice and the measured rows (:func:`~btfcore.acquisition.adaptive.run_adaptive`; the committee:
        :func:`_loop_setup`).
    say : callable, optional
        ``say(line)``: an info line (a resumed run says how many steps it replays).

    Returns
    -------
    doc : dict
        ``report.json``'s document with ``report_json`` and ``report_html`` (the paths), ``reused``
        (``{"steps": [replayed, total]}``) and ``finished_before`` (a finished run's rerun).
    """
    from tasks.faults import kill_point
    from tasks.plan import write_plan
    from tasks.report import write_json

    if not 0 < target < 1:
        raise ValueError(f"--target-error {target} must lie in (0, 1): a relative L2 error of log Y (0.2 = 20 %)")
    loop = _loop_setup(truth_path, measured, model_path, cls, device_name, calibration, select)
    U, sigma, geometry, device, noise = loop.U, loop.sigma, loop.geometry, loop.device, loop.noise
    truth, truth_store, measure, (h, w) = loop.truth, loop.truth_store, loop.measure, loop.texture_shape
    compare = compare and truth is not None
    budget = min(budget or geometry.n_turn * geometry.n_leds, geometry.n_turn * geometry.n_leds)
    inputs = _journal_inputs(loop, cls, measured is None, {
        "target": target, "budget": budget, "seed": seed, "predictor": predictor, "weighting": weighting,
        "select": select, "measured_rows": measured_rows, "compare": compare, "sampling_steps": sampling_steps,
        **({"time_aware": True} if time_aware else {})})
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    journal_path = out / JOURNAL
    journal = open_journal(out, json_key(inputs), inputs, overwrite)
    replay = list(journal["steps"])                            # the steps a killed run finished
    if journal["finished"] and all((out / name).exists() for name in ACQUIRE_OUTPUTS):
        doc = json.loads((out / "report.json").read_text())      # a finished run: nothing to do
        return {**doc, "report_json": str(out / "report.json"), "report_html": str(out / "report.html"),
                "reused": {"steps": [len(replay), len(replay)]}, "finished_before": True}
    if replay and say is not None:
        say(f"btf acquire: {journal_path}: resuming after {len(replay)} recorded step(s), replayed (measured "
            "again, not chosen again)")
    if not journal_path.exists():
        kill_point("store-creating")                            # nothing written yet
        write_json(journal_path, journal)
        kill_point("store-created")                             # the empty journal in place, no step

    def on_record(step: dict[str, Any], recorded: dict[str, Any] | None) -> None:
        if recorded is not None:
            _check_replayed(step, recorded, journal_path)
            return
        journal["steps"].append(step)
        write_json(journal_path, journal)
        kill_point("chunk-done")                                # one more step on disk

    try:
        rec = adaptive_material(U, sigma, geometry, truth, noise, device, target=target, budget=budget, seed=seed,
                                light_dir=truth_store.light_dir if compare else None,
                                view_dir=truth_store.view_dir if compare else None, sampling_steps=sampling_steps,
                                plans_dir=out / "plans", predictor=predictor, weighting=weighting,
                                replay=replay, on_record=on_record, time_aware=time_aware, measure=measure,
                                n_tx=h * w, select=select, committee=loop.committee, measured_rows=measured_rows)
    except AwaitingShot as wait:                               # a dome's loop: the next shot is to be taken
        plan = out / "plans" / f"step_{wait.step:03d}.json"
        write_plan(adaptive_plan(device, [wait.group]), plan, plan.with_suffix(".csv"), device=device)
        t, led = divmod(wait.group, geometry.n_leds)
        return {"schema": "btf-adaptive-acquisition", "waiting": {
            "step": wait.step, "turntable": int(t), "led": int(led), "plan": str(plan), "measurement": str(wait.path)},
            "steps_done": len(journal["steps"]), "reused": {"steps": [len(replay), len(journal["steps"])]},
            "finished_before": False}
    plan_doc = write_plan(adaptive_plan(device, rec["groups"]), out / "plan.json", out / "plan.csv", device=device)
    summary = {"schema": "btf-adaptive-acquisition", "material": loop.material, "class": cls, "target": target,
               **({"truth": str(truth_path)} if measured is None else
                  {"measured": str(measured), "exposure": dict(measure.exposures)}),   # steps whose gain is read
               "model": str(model_path), "device": device.name,
               "geometry": [geometry.n_turn, geometry.n_cam, geometry.n_leds], "record": rec,
               "predicted_time_s": plan_doc["predicted_time"]["total_s"]}
    paths = write_adaptive_report(out, summary)
    journal["finished"] = True                                  # every output in place
    write_json(journal_path, journal)
    return {**summary, **paths, "reused": {"steps": [len(replay), len(rec["steps"])]}, "finished_before": False}


