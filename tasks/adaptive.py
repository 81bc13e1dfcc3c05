"""Adaptive capture on simulated data (``btf acquire --adaptive``) and in the acquisition evaluation.

The numerics are :mod:`btfcore.acquisition.adaptive`; this module feeds them:

* the **executor** of a step: the simulator measures one group's rows from a noise-free truth BTF with
  the evaluation's noise model (:func:`btfcore.acquisition.band_evaluation.noisy_single` at an ideal
  auto exposure), and every step's shot is written as a plan file (``plans/step_NNN.json``, a
  :class:`~btfcore.acquisition.plan.CapturePlan` of one shot) that a dome operator could execute;
* the **fixed samplings** it is compared with, on the same material, basis, solver and noise: the
  thesis' random-swap samplings of n_s = 100, 200, 400 (light, turntable) pairs scaled to the device
  (paper 4 §5.2, :func:`btfcore.acquisition.strategies.scaled_pairs`) and the 7x7 parabolic map
  (paper 1 Fig. 3b);
* ``btf acquire --adaptive`` itself, with its step journal, is :mod:`tasks.adaptive_acquire`;
* the **report** (``report.json``, ``report.html`` with error against shots) and the **evaluation
  section** (:func:`evaluate_adaptive`): the loop leave-one-out on every held-out material of the
  truth database with its class's leave-one-out ALS basis, one Dask task per material, and the bars.

docs/adaptive-capture.md describes the method, the predictor and the measured numbers.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from btfcore.acquisition.adaptive import (PREDICTION_KEYS, STOP_PATIENCE, AdaptiveResult, AdaptiveState, basis_floor,
                                         first_stop, group_pairs, log_y_error, run_adaptive, stop_index)
from btfcore.acquisition.band_evaluation import noisy_single
from btfcore.acquisition.noise import SensorNoise, bracket_gain, exposure_gain
from btfcore.acquisition.plan import CapturePlan, ExposureModel, Shot
from btfcore.acquisition.sampling import parabolic_map_sampling, random_swap
from btfcore.acquisition.strategies import THESIS_N_S, Geometry, row_groups, scaled_pairs
from btfcore.acquisition.time_model import TimeModelParams, predict_time
from btfcore.dome import Device
from btfcore.model.colour import REC709_LUMA
from tasks.compute import Progress, wait_all

__all__ = ["ADAPTIVE_VERSION", "AwaitingShot", "committee_bases", "adaptive_plan", "adaptive_material",
           "evaluate_adaptive", "fixed_curves", "measured_executor", "simulated_measure",
           "step_measurement", "write_adaptive_report"]

#: Raised when the adaptive records' meaning changes (their reuse key includes it). 8: records hold the class
#: basis' floor (:func:`~btfcore.acquisition.adaptive.basis_floor`); probes are drawn by brightness stratum.
ADAPTIVE_VERSION = 8

#: A fixed sampling's error at most this many times the class basis' floor counts as at the floor.
AT_FLOOR = 1.1


# --------------------------------------------------------------------------- executor and scores


def simulated_measure(truth: np.ndarray, noise: SensorNoise, seed: Sequence[int]) -> Any:
    """``measure(group, rows) -> (measured (n_cam, n_tx, 3), gain (n_cam,))`` from a truth ``(n_lv, n_tx, 3)``.

    Each image is exposed so that its brightest noise-free value sits at the noise model's fill (the
    evaluation's ideal auto exposure); the noise of a group comes from ``seed + [group]``.
    """
    def measure(group: int, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = truth[rows]
        gain = exposure_gain(x.reshape(len(rows), -1).max(axis=1), noise)
        y = noisy_single(x[:, None], 0, (gain, gain), noise, [*seed, int(group)])[:, 0]
        return y, gain
    return measure


class AwaitingShot(Exception):
    """A step's measurement is not there yet (:func:`measured_executor`): the dome has to take its shot."""

    def __init__(self, step: int, group: int, path: Path) -> None:
        super().__init__(f"step {step}: no measurement at {path}")
        self.step, self.group, self.path = step, group, path


def step_measurement(folder: Path, step: int) -> Path:
    """Where the ingested shot of ``step`` is read from: ``FOLDER/step_NNN.zarr`` (a ``btf ingest`` output)."""
    return Path(folder) / f"step_{step:03d}.zarr"


def measured_executor(folder: Path, noise: SensorNoise, correction: Any = None) -> Any:
    """``measure(group, rows) -> (measured (n_cam, n_tx, 3), gain (n_cam,))`` of a real dome's shots.

    The ``k``-th call reads step ``k``'s measurement store (:func:`step_measurement`: ``btf ingest`` of the
    capture of ``plans/step_NNN.json``), whose rows must be the group's single-light rows. With
    ``correction`` (a :class:`tasks.reconstruct.RowCorrection` of the white standard's LED gains and the
    colour matrix, as ``btf reconstruct`` corrects single-light rows) each row is divided by its LED's gain
    and mapped by the matrix; without, rows are taken as ingested (the relative weights make the fit
    indifferent to one scale for all rows, not to per-LED gains). The noise model's gain of each image
    is read from the capture the store was ingested from (its ``source``): the electrons per DN/s of the
    longest frame of the row's bracket that did not saturate at its brightest value
    (:func:`btfcore.acquisition.noise.bracket_gain`, with the capture's sensor gain, black and white
    levels). Where that capture cannot be read (moved, or a sensor without a recorded gain) the gain is
    that of the simulator's ideal auto exposure (:func:`simulated_measure`) and the step counts in
    ``measure.exposures["assumed"]`` (else ``["capture"]``), which the run's summary reports. A missing
    store raises :class:`AwaitingShot`.
    """
    from tasks.stores.measurement import open_measurement_store, read_G

    calls = [0]
    exposures = {"capture": 0, "assumed": 0}

    def measure(group: int, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        path = step_measurement(folder, calls[0])
        if not path.exists():
            raise AwaitingShot(calls[0], group, path)
        calls[0] += 1
        store = open_measurement_store(path)
        G = read_G(store).tocsr()
        if np.any(np.diff(G.indptr) != 1):
            raise ValueError(f"{path}: not a single-light shot (a row of G measures several LEDs); ingest the "
                             "capture of this step's plan")
        found = G.indices
        if sorted(found.tolist()) != sorted(np.asarray(rows).tolist()):
            raise ValueError(f"{path}: measures rows {sorted(found.tolist())}, but step {calls[0] - 1}'s group "
                             f"{group} is rows {sorted(np.asarray(rows).tolist())}; ingest the capture of "
                             f"plans/step_{calls[0] - 1:03d}.json there")
        order = [int(np.flatnonzero(found == r)[0]) for r in rows]
        y = np.asarray(store["measured"][...], dtype=np.float32)[order]
        y = y.reshape(len(rows), -1, 3) / np.asarray(G.data, dtype=np.float32)[order, None, None]
        ingested = y.reshape(len(rows), -1).max(axis=1)                     # DN/s, as the frames saw it
        if correction is not None:
            y = correction.rows(y, correction.gain[np.asarray(rows)])
        bright = y.reshape(len(rows), -1).max(axis=1)
        if not np.all(np.isfinite(y)) or np.any(bright <= 0) or np.any(ingested <= 0):
            raise ValueError(f"{path}: a row is dark, or holds NaN/Inf; check the shot's exposure and ingest it "
                             "again")
        bracket = _capture_bracket(store, np.asarray(order))
        if bracket is None:
            exposures["assumed"] += 1
            return y, exposure_gain(bright, noise)
        exposures["capture"] += 1
        # electrons per DN/s of the frames, then per unit of the corrected rows (their scale is bright / ingested)
        return y, bracket_gain(ingested, *bracket) * ingested / bright

    measure.exposures = exposures
    return measure


def _capture_bracket(store: Any, order: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """``(exposure times (rows, n_exp), saturation DN, e/DN)`` of a measurement store's rows ``order`` from the
    capture it was ingested from (its ``source``); None where that capture or its sensor's gain cannot be read."""
    from tasks.stores import open_capture_store

    attrs = dict(store.attrs)
    source = attrs.get("source")
    if not source or not str(attrs.get("units", "")).startswith("DN/s"):
        return None
    try:
        capture = open_capture_store(source)
    except Exception:  # noqa: BLE001 - a moved or unreadable capture: the ideal auto exposure stands in
        return None
    e_per_dn = (capture.meta.sensor or {}).get("gain_e_per_dn")
    if not e_per_dn:
        return None
    t, c, i = np.asarray(store["meas_index"][...])[order].T
    times = np.asarray(capture.exposure_time)[t, c, i]
    return times, float(capture.meta.white_level - capture.meta.black_level), float(e_per_dn)


def _luma(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, dtype=np.float64) @ REC709_LUMA


def truth_score(truth: np.ndarray) -> Any:
    """``score(B) -> relative L2 of log Y`` of a reconstruction ``B`` (n_lv, n_tx, 3) against the truth
    (simulated data)."""
    truth_y = _luma(truth)
    return lambda B: log_y_error(_luma(B), truth_y)


def fixed_curves(U: np.ndarray, sigma: np.ndarray, geometry: Geometry, truth: np.ndarray, noise: SensorNoise,
                 light_dir: np.ndarray, view_dir: np.ndarray, seed: int, sampling_steps: int = 1500,
                 n_thesis: Sequence[int] = THESIS_N_S, weighting: str = "relative",
                 measured_rows: str = "model") -> list[dict[str, Any]]:
    """Errors of the fixed samplings on one material: random swap of scaled n_s pairs and the 7x7 parabolic map.

    Each is measured by the same simulator (:func:`simulated_measure`, one seed per group) and reconstructed
    by the same solve as the adaptive loop (:class:`~btfcore.acquisition.adaptive.AdaptiveState` with the same
    ``weighting`` and ``measured_rows``), so the curves differ only in the sampling. The parabolic map's
    light/view pairs are shot as the (turntable, LED) groups that hold them, with all cameras (a dome
    captures every camera of a shot). Returns ``[{"name", "n_thesis", "n_shots", "n_meas", "error"}]``.
    """
    measure = simulated_measure(truth, noise, [seed, 1])
    score = truth_score(truth)
    n_pairs = geometry.n_turn * geometry.n_leds
    US = U * sigma[None, :]

    def solve(groups: np.ndarray) -> float:
        state = AdaptiveState(U, sigma, geometry, noise, n_tx=truth.shape[1], weighting=weighting,
                              measured_rows=measured_rows)
        for grp in groups:
            state.add(int(grp), *measure(int(grp), state.rows_of(int(grp))))
        return score(state.reconstruction())

    out = []
    for n in n_thesis:
        n_s = scaled_pairs(n, n_pairs)
        k_s = min(U.shape[1], n_s * geometry.n_cam)
        sel = random_swap(US[:, :k_s], n_s, groups=row_groups(geometry, geometry.n_leds), max_steps=sampling_steps,
                          seed=seed + n)
        out.append({"name": f"random swap n_s={n} (scaled {n_s})", "n_thesis": int(n), "n_shots": int(n_s),
                    "n_meas": int(n_s * geometry.n_cam), "error": solve(np.asarray(sel.units))})
    pmap = np.unique(np.asarray(parabolic_map_sampling(light_dir, view_dir, 7), dtype=np.int64))
    groups = np.unique(row_groups(geometry, geometry.n_leds)[pmap])
    out.append({"name": "7x7 parabolic map (its groups, all cameras)", "n_thesis": None, "n_shots": int(len(groups)),
                "n_meas": int(len(groups) * geometry.n_cam), "error": solve(groups)})
    return out


# --------------------------------------------------------------------------- plans


def adaptive_plan(device: Device, groups: Sequence[int], exposure: ExposureModel | None = None) -> CapturePlan:
    """The shots of the groups in acquisition order (single light, all cameras): a ``sparse`` plan whose
    order is the loop's, not sorted by turntable position (the loop decides the next shot from the last)."""
    exposure = exposure or ExposureModel()
    cams = tuple(range(device.n_cam))
    pairs = group_pairs(np.asarray(groups, dtype=np.int64), device.n_leds)
    shots = [Shot(int(t), (int(led),), cams, exposure.bracket_ms(1), "single") for t, led in pairs]
    return CapturePlan(device=device.name, n_turn=device.n_turn, n_cam=device.n_cam, n_leds=device.n_leds,
                       turntable_angle_deg=tuple(device.turntable_angle_deg.tolist()), strategy="sparse",
                       shots=tuple(shots), parameters={"exposure": exposure.to_dict(), "adaptive": True,
                                                       "n_selected": len(shots)})


# --------------------------------------------------------------------------- one material


def shot_times(device: Device, params: TimeModelParams | None = None) -> dict[str, float]:
    """``{"shot_s", "move_s"}``: the time model's seconds for one group's shot on ``device`` (a one-shot
    plan, :func:`adaptive_plan`) and for a turntable move (paper 4 §5.2's time model,
    :mod:`btfcore.acquisition.time_model`), for the time-aware choice of
    :func:`~btfcore.acquisition.adaptive.run_adaptive`."""
    params = params or TimeModelParams()
    return {"shot_s": float(predict_time(adaptive_plan(device, [0]), params).total_s),
            "move_s": float(params.turntable_move_s)}


def adaptive_material(U: np.ndarray, sigma: np.ndarray, geometry: Geometry, truth: np.ndarray | None,
                      noise: SensorNoise, device: Device, *, target: float, budget: int, seed: int,
                      light_dir: np.ndarray | None = None,
                      view_dir: np.ndarray | None = None, sampling_steps: int = 1500, plans_dir: Path | None = None,
                      predictor: str = "posterior", weighting: str = "relative",
                      replay: Sequence[dict[str, Any]] = (),
                      on_record: Callable[[dict[str, Any], dict[str, Any] | None], None] | None = None,
                      time_aware: bool = False, measure: Callable[..., Any] | None = None,
                      n_tx: int | None = None, select: str = "posterior",
                      committee: Sequence[tuple[np.ndarray, np.ndarray]] = (),
                      measured_rows: str = "model") -> dict[str, Any]:
    """The loop on one simulated material (truth ``(n_lv, h, w, 3)``), with the fixed samplings beside it;
    or, with ``measure`` (:func:`measured_executor`: a dome's shots) and ``n_tx``, on measured shots
    (``truth`` None: no true error, no fixed samplings).

    With ``plans_dir`` every step's shot is written there as ``step_NNN.json`` / ``.csv`` (a plan of one
    shot, with its predicted time). ``replay``: the records of the first steps of an earlier run of the
    same inputs (a journal's); their groups are measured again instead of chosen
    (:func:`~btfcore.acquisition.adaptive.run_adaptive`'s ``replay``), their plans are not written again
    (unless missing) and the returned record holds them as given (with their CPU seconds).
    ``on_record(step, recorded)`` is called after every step (its plan written): ``step`` its plain-JSON
    record, ``recorded`` the replayed record or None for a step this run chose. ``time_aware``: the next
    group maximises the expected reduction per second of the time model (:func:`shot_times`), so that
    a turntable move must buy its 5 s. ``select``, ``committee``, ``measured_rows``: how the next group is
    chosen and the measured rows reconstructed (:func:`~btfcore.acquisition.adaptive.run_adaptive`; the fixed
    samplings get the same ``measured_rows``). Returns a plain-JSON record (steps, predicted time, fixed curves).
    """
    from tasks.plan import write_plan

    if truth is not None:
        truth = np.asarray(truth, dtype=np.float32).reshape(truth.shape[0], -1, 3)
        measure, n_tx = simulated_measure(truth, noise, [seed, 0]), truth.shape[1]

    def on_step(step: Any) -> None:
        recorded = replay[step.step] if step.step < len(replay) else None
        if plans_dir is not None:
            path = plans_dir / f"step_{step.step:03d}.json"
            if recorded is None or not path.exists():
                write_plan(adaptive_plan(device, [step.group]), path, path.with_suffix(".csv"), device=device)
        if on_record is not None:
            on_record(step.to_dict(), recorded)

    result: AdaptiveResult = run_adaptive(U, sigma, geometry, noise, measure, n_tx=int(n_tx), target=target,
                                          budget=budget, seed=seed,
                                          score=None if truth is None else truth_score(truth), on_step=on_step,
                                          predictor=predictor, weighting=weighting, select=select,
                                          committee=committee, measured_rows=measured_rows,
                                          replay=[int(s["group"]) for s in replay],
                                          **(shot_times(device) if time_aware else {}))
    plan = adaptive_plan(device, result.groups)
    steps = [dict(s) for s in replay] + [s.to_dict() for s in result.steps[len(replay):]]
    record = {**result.to_dict(), "steps": steps, "pairs": group_pairs(result.groups, geometry.n_leds).tolist(),
              "predicted_time": predict_time(plan, TimeModelParams()).to_dict()}
    if truth is not None and light_dir is not None and view_dir is not None:
        record["fixed"] = fixed_curves(U, sigma, geometry, truth, noise, light_dir, view_dir, seed, sampling_steps,
                                       weighting=weighting, measured_rows=measured_rows)
        record["basis_floor"] = basis_floor(U, sigma, geometry, truth, weighting)
    return record


def predictor_of(rec: dict[str, Any]) -> str:
    """The predictor a loop's record stopped on (``settings['predictor']``; records before it: the posterior)."""
    return rec.get("settings", {}).get("predictor", "posterior")


def prediction(step: dict[str, Any], predictor: str) -> float:
    """A step record's prediction by ``predictor`` (:data:`~btfcore.acquisition.adaptive.PREDICTION_KEYS`)."""
    return step[PREDICTION_KEYS[predictor]]


def shots_to_reach(steps: Sequence[dict[str, Any]], error: float) -> int | None:
    """Shots after which the true error first is at most ``error`` (None: never within the run)."""
    for s in steps:
        if s.get("true") is not None and s["true"] <= error:
            return int(s["n_shots"])
    return None


# --------------------------------------------------------------------------- report


def plot_curves(records: dict[str, dict[str, Any]], path: Path, title: str) -> str:
    """Error against shots: adaptive (true and predicted) and the fixed samplings, one panel per material."""
    from tasks.report import pyplot, save_figure

    plt = pyplot()
    n = len(records)
    cols = min(n, 3)
    fig, axes = plt.subplots((n + cols - 1) // cols, cols, figsize=(4.2 * cols, 3.2 * ((n + cols - 1) // cols)),
                             squeeze=False)
    for ax, (name, rec) in zip(axes.ravel(), records.items()):
        shots = [s["n_shots"] for s in rec["steps"]]
        ax.plot(shots, [100 * (s["true"] or np.nan) for s in rec["steps"]], "-", color="C0", label="adaptive, true")
        ax.plot(shots, [100 * s["predicted"] for s in rec["steps"]], "--", color="C0", label="adaptive, predicted")
        ax.plot(shots, [100 * s["predicted_cv"] for s in rec["steps"]], ":", color="C2", label="adaptive, CV")
        if predictor_of(rec) == "probes":
            ax.plot(shots, [100 * s["predicted_probes"] for s in rec["steps"]], "-.", color="C4",
                    label="adaptive, probes")
        fixed = [f for f in rec.get("fixed", []) if f["n_thesis"] is not None]
        if fixed:
            ax.plot([f["n_shots"] for f in fixed], [100 * f["error"] for f in fixed], "s-", color="C1",
                    label="random swap (n_s 100/200/400 scaled)")
        for f in rec.get("fixed", []):
            if f["n_thesis"] is None:
                ax.plot([f["n_shots"]], [100 * f["error"]], "^", color="C3", label="7x7 parabolic map")
        if rec.get("basis_floor") is not None:
            ax.axhline(100 * rec["basis_floor"], color="0.5", lw=0.8, ls=(0, (1, 2)),
                       label="every row, noise-free, from the basis")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("shots (camera-parallel groups)")
        ax.set_ylabel("log Y relative L2 [%]")
        ax.set_ylim(bottom=0)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


def write_adaptive_report(out_dir: str | os.PathLike, summary: dict[str, Any]) -> dict[str, str]:
    """``report.json`` and ``report.html`` (steps, error against shots, plans) of ``btf acquire --adaptive``."""
    from tasks.html_report import format_number, write_html
    from tasks.report import write_json

    out = Path(out_dir)
    write_json(out / "report.json", summary)
    rec = summary["record"]
    fig = plot_curves({summary["material"]: rec}, out / "error_vs_shots.png", "error against shots")
    probes = predictor_of(rec) == "probes"
    steps = [["step", "turntable", "LED", "shots", "predicted [%]", "CV predicted [%]"]
             + (["probe", "probes' prediction [%]"] if probes else []) + ["true [%]", "residual s [relative]",
                                                                          "CPU per step [s]"]]
    steps += [[s["step"], s["turntable"], s["led"], s["n_shots"], round(100 * s["predicted"], 2),
               round(100 * s["predicted_cv"], 2)]
              + (["yes" if s["probe"] else "", round(100 * s["predicted_probes"], 2)] if probes else [])
              + [None if s["true"] is None else round(100 * s["true"], 2), round(s["residual_s"], 4),
                 round(s["cpu_s"], 4)] for s in rec["steps"]]
    fixed = [["sampling", "shots", "measured rows", "true error [%]"]] + [
        [f["name"], f["n_shots"], f["n_meas"], round(100 * f["error"], 2)] for f in rec.get("fixed", [])]
    head = {"material": summary["material"], "stopped by": rec["stopped"], "shots": rec["n_shots"],
            "target [%]": 100 * summary["target"], "predictor": predictor_of(rec),
            "final predicted [%]": round(100 * prediction(rec["steps"][-1], predictor_of(rec)), 2),
            "final true [%]": None if rec["steps"][-1]["true"] is None else round(100 * rec["steps"][-1]["true"], 2),
            "predicted acquisition time [s]": round(rec["predicted_time"]["total_s"], 1)}
    if rec.get("basis_floor") is not None:
        head["class basis' floor (every row, noise-free) [%]"] = round(100 * rec["basis_floor"], 2)
    sections = [{"title": "Error against shots",
                 "text": ["Adaptive: every step one (turntable, LED) group shot by all cameras, chosen by the expected "
                          "reduction of the predicted error given the measurements so far; the fixed samplings on "
                          "the same material, basis, Tikhonov solve and noise (docs/adaptive-capture.md). "
                          f"Plans of every step: {format_number(len(rec['steps']))} files in plans/."],
                 "figures": [{"file": fig, "caption": "log Y relative L2 error against shots"}]},
                {"title": "Fixed samplings", "table": fixed if len(fixed) > 1 else None},
                {"title": "Steps", "table": steps}]
    write_html(out / "report.html", "Adaptive capture (btf acquire --adaptive)", head, sections)
    return {"report_json": str(out / "report.json"), "report_html": str(out / "report.html")}


# --------------------------------------------------------------------------- the evaluation's section


def committee_bases(model: zarr.Group, exclude: str | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The committee of the adaptive loop's committee selection: every per-material ALS basis
    ``materials/<id>/als`` of a model store (``btf build-db``'s or the evaluation's) but ``exclude``'s,
    as ``(U, sigma)``, in material order."""
    from tasks.model import read_basis

    if "materials" not in model:
        return []
    out = []
    for mid in sorted(model["materials"].group_keys()):
        where = f"materials/{mid}/als"
        if mid != exclude and where in model and "U" in model[where]:
            fit = read_basis(model, where)
            out.append((np.asarray(fit.U, dtype=np.float64), np.asarray(fit.sigma, dtype=np.float64)))
    return out


def _adaptive_task(model_path: str, materials: list[Any], material_id: str, settings: Any, config: Any,
                   fixed_n400: float | None, record_path: str, key: str) -> dict[str, Any]:
    """One held-out material of the evaluation (a Dask task): its leave-one-out ALS basis, the loop to the
    budget of the thesis' n_s = 400 scaled, and the fixed samplings; stored under ``key``. The committee
    (``config.adaptive_select == 'committee'``) is every other material's own ALS basis."""
    from tasks.evaluate_acquisition.graph import material_geometry, material_index, leave_one_out_bases
    from tasks.evaluate_acquisition.reuse import write_record

    m = next(x for x in materials if x.material_id == material_id)
    als = leave_one_out_bases(model_path, materials, material_id, settings)["als"]
    committee = (committee_bases(zarr.open_group(model_path, mode="r", zarr_format=3), exclude=material_id)
                 if config.adaptive_select == "committee" else [])
    geometry = material_geometry(m)
    group = zarr.open_group(m.path, mode="r", zarr_format=3)
    truth = np.asarray(group["btf"][...], dtype=np.float32)
    device = config.build_device()
    noise = SensorNoise(float(device.sensor.full_well_e), float(device.sensor.read_noise_e), config.fill)
    budget = scaled_pairs(THESIS_N_S[-1], geometry.n_turn * geometry.n_leds)
    seed = config.seed + material_index(material_id) % 100000
    rec = adaptive_material(np.asarray(als.U, dtype=np.float64), np.asarray(als.sigma, dtype=np.float64), geometry,
                            truth, noise, device, target=0.0, budget=budget, seed=seed,
                            light_dir=np.asarray(group["light_dir"][...]), view_dir=np.asarray(group["view_dir"][...]),
                            sampling_steps=config.sampling_steps, select=config.adaptive_select,
                            committee=committee, measured_rows=config.adaptive_rows,
                            predictor=config.adaptive_predictor)
    rec["class"] = m.cls
    rec["fixed_n400_evaluation"] = fixed_n400
    return write_record(record_path, key, rec)


def evaluate_adaptive(model_path: str, materials: list[Any], config: Any, client: Any, out_dir: str | os.PathLike,
                      result: dict[str, Any], key: str, progress: Progress | None = None) -> dict[str, Any]:
    """The adaptive loop leave-one-out on every held-out material, one Dask task each, reused by ``key``;
    ``progress(done, total)`` after each material's loop (the ones not reused).

    Returns the section's summary: per material the steps and fixed curves, and the bars
    (:func:`adaptive_bars`).
    """
    from tasks.evaluate_acquisition.reuse import read_record

    out = Path(out_dir) / "adaptive"
    out.mkdir(parents=True, exist_ok=True)
    key = f"{key}/adaptive-{ADAPTIVE_VERSION}-{config.adaptive_select}-{config.adaptive_rows}" + (
        f"-{config.adaptive_predictor}" if config.adaptive_predictor != "posterior" else "")
    records, futures = {}, {}
    for m in materials:
        path = out / f"{m.material_id}.json"
        rec = read_record(path, key)
        if rec is not None:
            records[m.material_id] = rec
            continue
        n400 = result["materials"][m.material_id]["scores"].get(f"sparse-tikhonov-n{THESIS_N_S[-1]}", {})
        futures[m.material_id] = client.submit(_adaptive_task, model_path, materials, m.material_id,
                                               config.model_settings(), config, n400.get("rel_l2_log_y"), str(path),
                                               key, pure=False)
    done = dict(zip(futures, wait_all(list(futures.values()), progress)))
    records.update(done)
    records = {m.material_id: records[m.material_id] for m in materials}
    figure = plot_curves(records, out / "error_vs_shots.png", "adaptive against fixed samplings (held out)")
    return {"materials": records, "bars": adaptive_bars(records), "figure": f"adaptive/{figure}",
            "reused": [len(materials) - len(futures), len(materials)]}


def adaptive_bars(records: dict[str, dict[str, Any]], structured: Sequence[str] = ("carpet", "stone", "leather"),
                  ) -> dict[str, Any]:
    """The issue's bars on the evaluation's records.

    (1) per structured class, the mean over its held-out materials of the shots adaptive needs to reach
    the true error the fixed random swap reaches with the thesis' n_s = 400 (scaled; the same simulator),
    against that n_s: met when at least 2x fewer in every class (a material that never reaches it counts
    its whole budget). (2) the predicted error at the stop within 25 % of the true error on >= 90 % of
    the materials.
    """
    per_class: dict[str, dict[str, Any]] = {}
    for mid, rec in records.items():
        fixed = next(f for f in rec["fixed"] if f["n_thesis"] == THESIS_N_S[-1])
        need = shots_to_reach(rec["steps"], fixed["error"])
        c = per_class.setdefault(rec["class"], {"n_s": fixed["n_shots"], "shots": [], "never": 0,
                                                "shots_to_evaluation_n400": [], "never_evaluation": 0,
                                                "n400_at_floor": 0, "with_floor": 0})
        c["shots"].append(need if need is not None else rec["n_shots"])
        c["never"] += need is None
        if rec.get("basis_floor") is not None:                # records before ADAPTIVE_VERSION 8 have none
            c["with_floor"] += 1
            c["n400_at_floor"] += fixed["error"] <= AT_FLOOR * rec["basis_floor"]
        if rec.get("fixed_n400_evaluation") is not None:      # the evaluation's own paper-4 solve (unweighted)
            need_e = shots_to_reach(rec["steps"], rec["fixed_n400_evaluation"])
            c["shots_to_evaluation_n400"].append(need_e if need_e is not None else rec["n_shots"])
            c["never_evaluation"] += need_e is None
    for c in per_class.values():
        c["mean_shots"] = float(np.mean(c["shots"]))
        c["ratio"] = c["n_s"] / c["mean_shots"]
        if c["shots_to_evaluation_n400"]:
            c["ratio_evaluation"] = c["n_s"] / float(np.mean(c["shots_to_evaluation_n400"]))
    bar1 = all(per_class[c]["ratio"] >= 2 and per_class[c]["never"] == 0 for c in structured if c in per_class)
    within = {}
    used = {predictor_of(rec) for rec in records.values()}
    shown = ["posterior", "cv"] + sorted(used - {"posterior", "cv"})
    for mid, rec in records.items():
        last = rec["steps"][-1]
        within[mid] = {p: abs(last[PREDICTION_KEYS[p]] - last["true"]) / last["true"] for p in shown
                       if last.get(PREDICTION_KEYS[p]) is not None}
    share = {p: float(np.mean([w[p] <= 0.25 for w in within.values() if p in w])) for p in shown}
    stop_share = float(np.mean([within[mid][predictor_of(rec)] <= 0.25 for mid, rec in records.items()]))
    return {"shots_to_fixed_n400": per_class, "bar1_met": bool(bar1), "prediction_rel_error_at_stop": within,
            "share_within_25pct": share, "predictor": sorted(used), "share_within_25pct_stop": stop_share,
            "bar2_met": bool(stop_share >= 0.9), "at_target_stop": target_stops(records)}


def target_stops(records: dict[str, dict[str, Any]], patience: int | None = None) -> dict[str, dict[str, float]]:
    """Bar 2 where the loop stops at a target instead of its budget, from the budget run's steps (the choice
    does not use the target, so a run with one takes the same steps up to its stop): for the fixed random
    swap's error at each of the thesis' n_s as the target, the step :func:`stop_index` stops at with
    ``patience`` (default: the run's, else :data:`STOP_PATIENCE`; the last step where none is), on the run's
    predictor from its :func:`~btfcore.acquisition.adaptive.first_stop` on.

    Returns ``{"n_s=N": {"share_within_25pct", "true_over_target_max", "true_over_target_median"}}``: how
    often the prediction at that stop is within 25 % of the true error, and how far the true error is then
    over the target asked for."""
    out: dict[str, dict[str, float]] = {}
    for n_s in THESIS_N_S:
        within, over = [], []
        for rec in records.values():
            target = next((f["error"] for f in rec["fixed"] if f["n_thesis"] == n_s), None)
            if target is None:
                continue
            settings, predictor = rec.get("settings", {}), predictor_of(rec)
            at = stop_index([prediction(s, predictor) for s in rec["steps"]], [s["n_shots"] for s in rec["steps"]],
                            target, first_stop(settings), patience if patience is not None else
                            settings.get("patience", STOP_PATIENCE))
            stop = rec["steps"][-1 if at is None else at]
            within.append(abs(prediction(stop, predictor) - stop["true"]) <= 0.25 * stop["true"])
            over.append(stop["true"] / target)
        if within:
            out[f"n_s={n_s}"] = {"share_within_25pct": float(np.mean(within)),
                                 "true_over_target_max": float(np.max(over)),
                                 "true_over_target_median": float(np.median(over))}
    return out


_RULES = {"committee": "the one whose rows hold the most squared log-Y error as a committee of the other "
                        "materials' ALS bases, fitted to the same measurements, sees it (where they disagree with "
                        "the class basis).",
          "posterior": "the one with the largest expected reduction of the coefficients' predicted error."}


_POSTERIOR_NOTE = ("These shares are of this run's materials: the posterior's settings were chosen on the "
                   "default seed's, and on another draw (--eval-seed 1) bar 2 is not met at any stop "
                   "(docs/adaptive-capture.md, \"A second draw of materials\"); --adaptive-predictor probes holds it "
                   "more often.")
_PROBES_NOTE = ("The loop shot a probe, a group drawn at random from one brightness quartile of the groups in "
                "turn, every third step after the start design, and predicted the error of the groups it left from "
                "the probes' (a regression on the committee's disagreement with an intercept per quartile, from the "
                "fifth probe on; a target is not tested before): its estimator was chosen among five on replays of "
                "three draws of materials (seeds 0-2), its other settings were not tuned. The probes cost shots to "
                "a given error (docs/adaptive-capture.md, \"Probes by brightness stratum\").")


def adaptive_sections(section: dict[str, Any] | None) -> list[dict[str, Any]]:
    """The acquisition report's section on adaptive capture (:func:`evaluate_adaptive`'s summary)."""
    if not section:
        return []
    bars = section["bars"]
    rows = [["class", "fixed n_s=400 (scaled) shots", "adaptive shots to its error, mean [shots]",
             "fixed / adaptive [ratio]",
             "materials that never reach it",
             f"fixed n_s=400 at the basis' floor (at most {AT_FLOOR:g}x) [materials]",
             "to the evaluation's paper-4 n_s=400 error: fixed / adaptive [ratio]"]]
    for cls, c in sorted(bars["shots_to_fixed_n400"].items()):
        rows.append([cls, c["n_s"], round(c["mean_shots"], 1), round(c["ratio"], 2), c["never"],
                     f"{c['n400_at_floor']} of {c['with_floor']}" if c.get("with_floor") else "-",
                     round(c["ratio_evaluation"], 2) if "ratio_evaluation" in c else "-"])
    probes = "probes" in bars.get("predictor", [])
    mats = [["material", "class", "shots", "true at stop [%]", "predicted [%]", "CV predicted [%]"]
            + (["probes' prediction [%]"] if probes else []) + ["fixed n400 [%]", "basis' floor [%]",
                                                                 "predicted time [s]"]]
    for mid, rec in section["materials"].items():
        last = rec["steps"][-1]
        n400 = next(f for f in rec["fixed"] if f["n_thesis"] == THESIS_N_S[-1])
        mats.append([mid, rec["class"], rec["n_shots"], round(100 * last["true"], 2), round(100 * last["predicted"], 2),
                     round(100 * last["predicted_cv"], 2)]
                    + ([round(100 * last["predicted_probes"], 2) if last.get("predicted_probes") is not None
                        else "-"] if probes else [])
                    + [round(100 * n400["error"], 2),
                       round(100 * rec["basis_floor"], 2) if rec.get("basis_floor") is not None else "-",
                       round(rec["predicted_time"]["total_s"], 1)])
    share = bars["share_within_25pct"]
    settings = next(iter(section["materials"].values())).get("settings", {})
    return [{"title": "Adaptive capture (leave-one-out; docs/adaptive-capture.md)",
             "text": ["Every held-out material captured one (turntable, LED) group at a time with its class's "
                      "leave-one-out ALS basis, to the budget of the thesis' n_s = 400 (scaled); each next group "
                      + _RULES.get(settings.get("select", "posterior"), "") + " Measured rows: "
                      + ("fused with their measurements." if settings.get("measured_rows") == "fused" else
                         "the basis' fit (paper 4 eq. 10).")
                      + " The fixed samplings are on the same material, basis, Tikhonov solve, measured-row rule "
                      "and simulated noise (the bar's comparison, of the sampling only); the last column "
                      "compares with the evaluation's own reconstruction of the fixed sampling (paper 4 eq. 10, "
                      "unweighted, every row from the basis), which differs in the solve as well. The basis' "
                      "floor is the error of the same solve from every row, noise-free: where the fixed "
                      "sampling's error is at it, the loop gets there only by measuring the rows where the "
                      "basis is wrong (docs/adaptive-capture.md, \"Where the fixed sampling ends\").",
                      f"Bar 1 (>= 2x fewer shots than fixed n_s = 400 to its error, every structured class): "
                      f"{'met' if bars['bar1_met'] else 'not met'}. Bar 2 (prediction at the stop within 25 % "
                      f"of the true error on >= 90 % of materials): {'met' if bars['bar2_met'] else 'not met'} "
                      f"(the loop's predictor: {', '.join(bars.get('predictor', ['posterior']))}; posterior "
                      f"{100 * share['posterior']:.0f} %, cross-validation {100 * share['cv']:.0f} %"
                      + (f", probes {100 * share['probes']:.0f} %" if "probes" in share else "") + "), "
                      "at the budget's stop. Stopped instead at a target (the fixed random swap's error at n_s, "
                      "the loop's steps up to it): "
                      + "; ".join(f"{n}: {100 * t['share_within_25pct']:.0f} % within 25 %, the true error up to "
                                  f"{t['true_over_target_max']:.2f}x the target"
                                  for n, t in bars.get("at_target_stop", {}).items()) + ". "
                      + (_PROBES_NOTE if probes else _POSTERIOR_NOTE)],
             "tables": [rows, mats],
             "figures": [{"file": section["figure"], "caption": "log Y error against shots, every held-out material"}]}]
