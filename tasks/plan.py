"""Acquisition plans on disk: JSON (complete) and CSV (one row per shot).

The JSON file holds the whole :class:`btfcore.acquisition.plan.CapturePlan` -- device name
and shape, strategy, parameters, shots -- plus the predicted acquisition time
of :mod:`btfcore.acquisition.time_model` with its breakdown and the model parameters used.
The CSV file is the operator's list: one row per shot with the turntable angle,
the LEDs on, the cameras, the shutter times and the number of exposure steps;
a few ``# key: value`` comment lines above the header carry what is needed to
read it back into a plan. Both read back to an equal plan (:func:`read_plan`).

:func:`plan_patterns` designs the basis-aware patterns of ``btf plan --strategy
patterns`` from a model store's class basis (issue 20,
:mod:`btfcore.acquisition.illumination_patterns`).

See ``docs/acquisition-planning.md``.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from btfcore.acquisition.hadamard import is_s_matrix_order, s_matrix
from btfcore.acquisition.plan import PLAN_SCHEMA, CapturePlan, ExposureModel, Shot, validate_plan
from btfcore.dome import Device
from btfcore.acquisition.time_model import TimeModelParams, predict_time
from tasks.staging import write_file

__all__ = ["CSV_COLUMNS", "plan_patterns", "plan_to_csv_text", "read_plan", "read_plan_json", "write_plan"]

#: Columns of the plan CSV, in order.
CSV_COLUMNS: tuple[str, ...] = (
    "shot", "turntable", "turntable_angle_deg", "leds", "cameras", "shutter_ms", "exposure_steps", "group",
)
_CSV_META = ("schema", "schema_version", "device", "strategy", "n_turn", "n_cam", "n_leds", "turntable_angle_deg",
             "parameters")


def _ids(values) -> str:
    return ";".join(str(int(v)) for v in values)


def _floats(values) -> str:
    return ";".join(repr(float(v)) for v in values)


def plan_to_csv_text(plan: CapturePlan) -> str:
    """The CSV form of a plan (comment lines with the plan's metadata, header, one row per shot)."""
    buf = io.StringIO()
    meta = plan.to_dict()
    for key in _CSV_META:
        buf.write(f"# {key}: {json.dumps(meta[key])}\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for i, s in enumerate(plan.shots):
        w.writerow([i, s.turntable, repr(plan.turntable_angle_deg[s.turntable]), _ids(s.leds), _ids(s.cameras),
                    _floats(s.shutter_ms), s.n_exposures, s.group])
    return buf.getvalue()


def write_plan(plan: CapturePlan, path_json: str | Path, path_csv: str | Path | None = None, *,
               device: Device | None = None, time_params: TimeModelParams | None = None,
               multiplexing: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write a plan as JSON (and CSV).

    Parameters
    ----------
    plan : CapturePlan
    path_json : str or Path
        The complete plan with its predicted acquisition time.
    path_csv : str or Path, optional
        One row per shot: turntable angle (deg), LEDs on (``;``-separated),
        cameras, shutter times (ms), exposure steps.
    device : Device, optional
        Validate the plan against it first.
    time_params : TimeModelParams, optional
        Parameters of the time prediction (default
        :class:`~btfcore.acquisition.time_model.TimeModelParams` (), whose overheads are
        the fit on VMV Table 2's multiplexed times).
    multiplexing : dict, optional
        The predicted multiplexing gain
        (:func:`btfcore.acquisition.plan.multiplexing_gain`); written as
        ``multiplexing_gain`` and ``multiplexing_loses`` (gain below 1) with the
        details under ``multiplexing``.

    Returns
    -------
    doc : dict
        What was written to ``path_json``.

    Raises
    ------
    ValueError
        If the plan names a turntable position, camera or LED ``device`` lacks.
    """
    if device is not None:
        validate_plan(plan, device)
    params = time_params or TimeModelParams()
    doc = plan.to_dict()
    doc["predicted_time"] = {**predict_time(plan, params).to_dict(), "model": params.to_dict()}
    if multiplexing is not None:
        doc["multiplexing_gain"] = float(multiplexing["gain"])
        doc["multiplexing_loses"] = bool(multiplexing["loses"])
        doc["multiplexing"] = dict(multiplexing)
    write_file(path_json, lambda tmp: tmp.write_text(json.dumps(doc, indent=1)))
    if path_csv is not None:
        write_file(path_csv, lambda tmp: tmp.write_text(plan_to_csv_text(plan)))
    return doc


def read_plan_json(path: str | Path) -> tuple[CapturePlan, dict[str, Any]]:
    """Read a plan JSON; return the plan and the whole document (with ``predicted_time``)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not a plan JSON file ({exc}); write it with tasks.plan.write_plan") from None
    if not isinstance(doc, dict) or doc.get("schema") != PLAN_SCHEMA[0]:
        raise ValueError(f"{path}: schema is {doc.get('schema') if isinstance(doc, dict) else None!r}, "
                         f"expected {PLAN_SCHEMA[0]!r}; write it with tasks.plan.write_plan")
    try:
        return CapturePlan.from_dict(doc), doc
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def _read_csv(path: Path) -> CapturePlan:
    meta: dict[str, Any] = {}
    body = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if line.startswith("#"):
            key, sep, value = line[1:].partition(":")
            if not sep:
                raise ValueError(f"{path}, line {n}: comment line is not '# key: value'")
            try:
                meta[key.strip()] = json.loads(value)
            except json.JSONDecodeError:
                raise ValueError(f"{path}, line {n}: value of {key.strip()!r} is not JSON") from None
        elif line.strip():
            body.append(line)
    if meta.get("schema") != PLAN_SCHEMA[0]:
        raise ValueError(f"{path}: the '# schema: \"{PLAN_SCHEMA[0]}\"' line is missing; "
                         "write the CSV with tasks.plan.write_plan")
    rows = list(csv.DictReader(body))
    if body and tuple(csv.reader(body[:1]).__next__()) != CSV_COLUMNS:
        raise ValueError(f"{path}: header must be {','.join(CSV_COLUMNS)}")
    shots = []
    angles = meta.get("turntable_angle_deg", [])
    for i, r in enumerate(rows):
        try:
            t = int(r["turntable"])
            shot = Shot(turntable=t, leds=tuple(int(v) for v in r["leds"].split(";")),
                        cameras=tuple(int(v) for v in r["cameras"].split(";")),
                        shutter_ms=tuple(float(v) for v in r["shutter_ms"].split(";")), group=r["group"])
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ValueError(f"{path}: shot {i}: {exc}") from None
        if int(r["exposure_steps"]) != shot.n_exposures:
            raise ValueError(f"{path}: shot {i}: exposure_steps {r['exposure_steps']} but "
                             f"{shot.n_exposures} shutter times")
        if 0 <= t < len(angles) and not math.isclose(float(r["turntable_angle_deg"]), angles[t], abs_tol=1e-9):
            raise ValueError(f"{path}: shot {i}: turntable_angle_deg {r['turntable_angle_deg']} is not the "
                             f"angle {angles[t]} of turntable position {t}")
        shots.append(shot)
    meta["shots"] = [s.to_dict() for s in shots]
    try:
        return CapturePlan.from_dict(meta)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def _check_s_matrix_orders(plan: CapturePlan, path: Path) -> None:
    """Refuse a multiplexed group (``"S19"``, ``"q2-S47"``) or ``s_matrix_order`` parameter whose S-matrix
    order does not exist (a prime with n % 4 == 3; VMV §3.2), naming the file, the first shot and the fix."""
    orders = [(f"shot {i} (group {shot.group!r})", int(m.group(1))) for i, shot in enumerate(plan.shots)
              if (m := re.search(r"(?:^|-)S(\d+)$", shot.group))]
    if isinstance(plan.parameters.get("s_matrix_order"), int):
        orders.append(("parameters.s_matrix_order", plan.parameters["s_matrix_order"]))
    for where, n in orders:
        if not is_s_matrix_order(n):
            why = f"no S-matrix of order {n}"
            try:
                s_matrix(n)                      # its message names why and the nearest valid orders
            except ValueError as exc:
                why = str(exc).split(" (use ")[0]
            raise ValueError(f"{path}: {where}: {why}; write the plan again with `btf plan`, which picks the "
                             "order for the device's LEDs")


def read_plan(path: str | Path, device: Device | None = None) -> CapturePlan:
    """Read a plan written by :func:`write_plan`, from its JSON or its CSV.

    Parameters
    ----------
    path : str or Path
        ``.json`` or ``.csv``.
    device : Device, optional
        Validate the plan against it.

    Returns
    -------
    plan : CapturePlan

    Raises
    ------
    ValueError
        Naming the file and shot of a malformed entry, or (with ``device``) the
        shot and id the device lacks.
    """
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such plan file")
    suffix = path.suffix.lower()
    if suffix == ".json":
        plan = read_plan_json(path)[0]
    elif suffix == ".csv":
        plan = _read_csv(path)
    else:
        raise ValueError(f"{path}: plan files end in .json or .csv, not {suffix or 'nothing'}")
    _check_s_matrix_orders(plan, path)
    if device is not None:
        try:
            validate_plan(plan, device)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    return plan


# --------------------------------------------------------------------------- basis-aware patterns (issue 20)


def _shutter_total_ms(plan: CapturePlan) -> float:
    return float(sum(sum(shot.shutter_ms) for shot in plan.shots))


def plan_patterns(model: str | Path, cls: str, device: Device, m: int, *, exposure: ExposureModel | None = None,
                  seed: int = 0, signal_fraction: float = 0.8, sweeps: int = 1) -> CapturePlan:
    """A ``patterns`` plan: ``m`` basis-aware binary LED patterns for the class' ALS basis of a model store.

    Parameters
    ----------
    model : path
        ``btf build-db`` output folder or its ``model.zarr``; its rows must be ``device``'s
        (turntable, camera, LED) rows.
    cls : str
        Material class (``classes/<cls>/als``).
    device : Device
    m : int
        Patterns per turntable position.
    exposure : ExposureModel, optional
        Shutter brackets of the shots (and of the S-matrix plans compared).
    seed : int
        Seed of the design's refinement order.
    signal_fraction : float
        The chosen shutter time as the fraction of the full well a typical single-LED image's brightest
        texel reaches (:class:`~btfcore.acquisition.illumination_patterns.PatternModel` ``shutter_fill``);
        brighter patterns are exposed shorter, to ``fill`` = 0.8.
    sweeps : int
        Refinement sweeps of :func:`~btfcore.acquisition.illumination_patterns.design_patterns`.

    Returns
    -------
    plan : CapturePlan
        Its ``parameters`` hold the model, class, basis size, the design's predicted relative error and
        ``comparison``: the predicted errors and times of the full S-matrix, of ``m`` S-matrix rows chosen on
        the same objective (equal shot count) and of as many S-matrix rows as fit in the patterns' total
        shutter time (equal exposure time).

    Raises
    ------
    ValueError
        Bad store, class or basis (names which), or a basis whose rows are not the device's.
    """
    from btfcore.acquisition.hadamard import multiplexing_patterns
    from btfcore.acquisition.illumination_patterns import PatternModel, design_patterns, expected_error, select_rows
    from btfcore.acquisition.noise import SensorNoise
    from btfcore.acquisition.plan import multiplexed_plan, patterns_plan
    from tasks.sample import open_model, read_class_basis

    group, store = open_model(model)
    U, sigma, _ = read_class_basis(group, store, cls, "als")
    n_rows = device.n_turn * device.n_cam * device.n_leds
    if U.shape[0] != n_rows:
        raise ValueError(f"{store}: classes/{cls}/als has {U.shape[0]} rows, device {device.name!r} "
                         f"{device.n_turn} x {device.n_cam} x {device.n_leds} = {n_rows} (turntable, camera, LED) "
                         "rows; plan for the device the model was built from")
    if int(m) < 1:
        raise ValueError(f"--patterns {m}: give at least one pattern")
    exposure = exposure or ExposureModel()
    noise = SensorNoise(float(device.sensor.full_well_e), float(device.sensor.read_noise_e))
    pm = PatternModel(U, sigma, device.n_leds, noise, shutter_fill=float(signal_fraction))
    S = multiplexing_patterns(device.n_leds)
    rows_m = select_rows(pm, S, min(int(m), S.shape[0]))[1]
    start = rows_m.patterns if int(m) <= S.shape[0] else None                # refine S-matrix rows (robust start)
    design = design_patterns(pm, int(m), seed=seed, sweeps=sweeps, start=start)
    full = multiplexed_plan(device, exposure)
    mine = patterns_plan(device, design.patterns, exposure)
    per_row = _shutter_total_ms(patterns_plan(device, S[:1], exposure, turntables=[0]))
    m_eq = int(min(S.shape[0], max(1, np.floor(_shutter_total_ms(mine) / device.n_turn / per_row))))
    rows_eq = select_rows(pm, S, m_eq)[1]

    def entry(d, plan: CapturePlan) -> dict[str, Any]:
        return {"m": d.m, "predicted_relative_error": d.relative_error,
                "predicted_time_s": predict_time(plan).total_s, "shutter_total_ms": _shutter_total_ms(plan)}

    comparison = {
        "full-s-matrix": entry(expected_error(pm, S), full),
        "s-matrix-rows-equal-shots": entry(rows_m, patterns_plan(device, rows_m.patterns, exposure)),
        "s-matrix-rows-equal-exposure-time": entry(rows_eq, patterns_plan(device, rows_eq.patterns, exposure)),
        "patterns": entry(design, mine),
    }
    parameters = {"model": str(store.resolve()), "class": cls, "basis": "als", "k": int(U.shape[1]),
                  "seed": int(seed), "signal_fraction": float(signal_fraction), "peak_factor": pm.peak_factor,
                  "full_well_e": noise.full_well_e, "read_noise_e": noise.read_noise_e, "fill": noise.fill,
                  "predicted_relative_error": design.relative_error, "objective": design.objective,
                  "leds_on": design.summary()["leds_on"], "comparison": comparison}
    return patterns_plan(device, design.patterns, exposure, parameters=parameters)
