"""Issue 20 study (not a speed benchmark): how many shots would a rule that knew the truth need?

Bar 1 asks the adaptive loop to reach, in half the shots or fewer, the error the thesis' fixed
optimised sampling reaches with n_s = 400 (scaled). This study bounds what any choice of groups
can do on the evaluation's held-out materials: a greedy *truth oracle* that, at every step after the
start design, measures the group whose shot lowers the true log-Y error most (each candidate's
simulated shot added to the state, the reconstruction recomputed with the loop's solve and
measured-row rule, scored against the truth). It is myopic (one shot ahead), so a better sequence
may exist, but no rule that sees only the measurements chooses with more knowledge.

The oracle compares candidates in luminance on a seeded subset of texels (``--texels``; the
measured rows fused in luminance); its sequence is then scored like the loop's (every texel,
linear RGB, :meth:`~btfcore.acquisition.adaptive.AdaptiveState.reconstruction`). The bases,
simulator seeds, noise and budget are the evaluation's (``tasks.adaptive._adaptive_task``), read
from its output folder; the loop's steps and the fixed n_s = 400 error come from its report.json.
About 4 minutes per material on one core.

    .venv/bin/python benchmarks/study_adaptive_oracle.py --db acq-db --eval acq \\
        [--materials 000-leather,006-leather] [--texels 256] [--workers 2] [--out oracle.json]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from btfcore.acquisition.adaptive import FUSE_S2_FLOOR, AdaptiveState, fuse_measured, start_groups
from btfcore.acquisition.noise import SensorNoise
from btfcore.model.colour import LOG_YUV_EPS, REC709_LUMA
from tasks.adaptive import THESIS_N_S, scaled_pairs, shots_to_reach, simulated_measure, truth_score
from tasks.evaluate_acquisition.config import EvaluationConfig
from tasks.evaluate_acquisition.graph import leave_one_out_bases, material_geometry, material_index
from tasks.model import discover

STRUCTURED = ("carpet", "stone", "leather")


def _luminance_error(state: AdaptiveState, s2: float, log_truth: np.ndarray, ss: float,
                     extra: tuple | None = None) -> float:
    """True relative L2 error of log Y on the state's texels, with one more group's shot ``extra``
    ``(rows, measured (n_cam, n_tx, 3), gain)`` added as :meth:`AdaptiveState.add` adds it; ``s2`` the fusion's
    relative model residual."""
    M, b = state.M, state.b.reshape(state.k, state.n_tx, 3) @ REC709_LUMA
    rows, measured, gain = state.rows, list(state.measured), state.gain
    if extra is not None:
        r, y, g = extra
        yl = y @ REC709_LUMA
        w = state._weights(np.sqrt(np.mean(yl ** 2, axis=1)))
        a = state.X[r] * np.sqrt(w)[:, None]
        M, b = M + a.T @ a, b + a.T @ (np.sqrt(w)[:, None] * yl)
        rows, measured, gain = np.concatenate([rows, r]), measured + [y], np.concatenate([gain, g])
    Y = state.X @ np.linalg.solve(M, b)
    if state.measured_rows == "fused" and len(rows):
        yl = np.concatenate(measured) @ REC709_LUMA
        Y[rows] = fuse_measured(np.repeat(Y[rows, :, None], 3, -1), np.repeat(yl[..., None], 3, -1), gain,
                                state.noise, max(s2, FUSE_S2_FLOOR))[..., 0]
    return float(np.sqrt(np.sum((np.log(np.maximum(Y, LOG_YUV_EPS)) - log_truth) ** 2) / ss))


def oracle_material(args: tuple[str, str, str, dict[str, Any], int]) -> dict[str, Any]:
    """The greedy truth oracle on one held-out material: its groups and true error after every shot."""
    db, model_path, material_id, config_dict, n_texels = args
    config = EvaluationConfig(**config_dict)
    materials = discover(db)
    m = next(x for x in materials if x.material_id == material_id)
    als = leave_one_out_bases(model_path, materials, material_id, config.model_settings())["als"]
    U, sigma = np.asarray(als.U, dtype=np.float64), np.asarray(als.sigma, dtype=np.float64)
    geometry = material_geometry(m)
    truth = np.asarray(zarr.open_group(m.path, mode="r", zarr_format=3)["btf"][...], dtype=np.float32)
    truth = truth.reshape(truth.shape[0], -1, 3)
    device = config.build_device()
    noise = SensorNoise(float(device.sensor.full_well_e), float(device.sensor.read_noise_e), config.fill)
    budget = scaled_pairs(THESIS_N_S[-1], geometry.n_turn * geometry.n_leds)
    seed = config.seed + material_index(material_id) % 100000
    measure = simulated_measure(truth, noise, [seed, 0])            # the loop's simulator and seed
    sub = np.sort(np.random.default_rng(seed).choice(truth.shape[1], min(n_texels, truth.shape[1]), replace=False))
    log_truth = np.log(np.maximum(truth[:, sub] @ REC709_LUMA, LOG_YUV_EPS))
    ss = float(np.sum(log_truth ** 2))
    state = AdaptiveState(U, sigma, geometry, noise, n_tx=len(sub), seed=seed, weighting="relative",
                          measured_rows=config.adaptive_rows)
    n0 = int(np.ceil(2 * state.k / geometry.n_cam))
    first = start_groups(U, sigma, geometry, n0)
    shots: dict[int, tuple] = {}

    def shot(group: int) -> tuple:
        if group not in shots:
            y, gain = measure(group, state.rows_of(group))
            shots[group] = (np.asarray(y)[:, sub], gain)
        return shots[group]

    t0 = time.perf_counter()
    for n in range(budget):
        if n < n0:
            group = first[n]
        else:
            s2 = float(state._model()["s2"])
            cand = np.setdiff1d(np.arange(state.n_groups), state.groups)
            errs = [_luminance_error(state, s2, log_truth, ss, (state.rows_of(int(c)), *shot(int(c)))) for c in cand]
            group = int(cand[int(np.argmin(errs))])
        state.add(group, *shot(group))
    # the oracle's sequence scored as the loop's: every texel, linear RGB, the state's reconstruction
    full = AdaptiveState(U, sigma, geometry, noise, n_tx=truth.shape[1], seed=seed, weighting=state.weighting,
                         measured_rows=config.adaptive_rows)
    score = truth_score(truth)
    curve = []
    for group in state.groups:
        full.add(group, *measure(group, full.rows_of(group)))
        curve.append(float(score(full.reconstruction())))
    return {"material": material_id, "class": m.cls, "groups": state.groups, "true": curve,
            "seconds": round(time.perf_counter() - t0, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--db", required=True, help="the evaluation's truth database (btf evaluate acquisition --db)")
    ap.add_argument("--eval", required=True, help="the evaluation's output folder (model.zarr, report.json)")
    ap.add_argument("--materials", default="", help="comma-separated material ids (default: the structured classes')")
    ap.add_argument("--texels", type=int, default=256, help="texels the oracle compares candidates on")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default="", help="write the results as JSON here")
    a = ap.parse_args()
    report = json.loads((Path(a.eval) / "report.json").read_text())
    config = {k: tuple(v) if isinstance(v, list) else v for k, v in report["config"].items()}
    records = report["adaptive"]["materials"]
    ids = a.materials.split(",") if a.materials else [k for k, r in records.items() if r["class"] in STRUCTURED]
    jobs = [(a.db, str(Path(a.eval) / "model.zarr"), mid, config, a.texels) for mid in ids]
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    with ProcessPoolExecutor(a.workers) as ex:
        results = list(ex.map(oracle_material, jobs))
    per_class: dict[str, dict[str, list[int]]] = {}
    print(f"{'material':<14}{'fixed n400':>11}{'loop shots':>11}{'oracle shots':>13}   oracle error at 17/33/67 shots")
    for res in results:
        rec = records[res["material"]]
        target = next(f["error"] for f in rec["fixed"] if f["n_thesis"] == THESIS_N_S[-1])
        budget = len(res["true"])
        loop = shots_to_reach(rec["steps"], target)
        oracle = shots_to_reach([{"n_shots": i + 1, "true": e} for i, e in enumerate(res["true"])], target)
        res.update(fixed_n400=target, loop_shots=loop, oracle_shots=oracle)
        c = per_class.setdefault(res["class"], {"loop": [], "oracle": []})
        c["loop"].append(loop or budget)
        c["oracle"].append(oracle or budget)
        at = " / ".join(f"{100 * res['true'][i - 1]:.2f}" for i in (17, 33, budget))
        print(f"{res['material']:<14}{100 * target:>10.2f}%{loop or 'never':>11}{oracle or 'never':>13}   {at} %")
    summary = {cls: {k: round(float(budget / np.mean(v)), 2) for k, v in c.items()} for cls, c in per_class.items()}
    print("budget / mean shots to the fixed n400 error, per class (loop, oracle):", summary)
    if a.out:
        Path(a.out).write_text(json.dumps({"materials": results, "ratio": summary}, indent=1))


if __name__ == "__main__":
    main()
