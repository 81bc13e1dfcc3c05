"""The thesis' claims (a)-(e) and its tables, computed from the evaluation's scores.

Every verdict is computed from the numbers beside it by the rule it states,
never written by hand (docs/evaluation.md, "Claims and measured numbers").
``result`` is :func:`tasks.evaluate_acquisition.graph.evaluate_materials`'
``{"materials": {id: {"class": str, "scores": {strategy: {metric: float}}}}}``;
errors are fractions here and per cent in the claims.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.reconstruct import LAMBDA_ALS
from btfcore.acquisition.strategies import THESIS_N_S, strategy_names
from btfcore.dome import Device, get_device
from tasks.evaluate_acquisition.config import STRUCTURED_CLASSES

#: The strategies of claims (a) and (b), paper 1 Table 2.
PAPER1_SAMPLED = ("abrdf-pmap7", "abrdf-optimized", "abtf-pmap7", "abtf-optimized")
#: The strategies of claim (c), VMV Table 1, in its order.
VMV_DENOISING = ("demultiplexed", "projection", "thresholded")


def class_means(result: dict[str, Any], metric: str = "rel_l2_log_y") -> dict[str, dict[str, float]]:
    """``{class: {strategy: mean of metric over the class' materials}}`` (errors in the metric's unit)."""
    by_class: dict[str, list[dict[str, Any]]] = {}
    for rec in result["materials"].values():
        by_class.setdefault(rec["class"], []).append(rec["scores"])
    return {cls: {name: float(np.mean([s[name][metric] for s in recs])) for name in recs[0]}
            for cls, recs in sorted(by_class.items())}


def overall_means(result: dict[str, Any], metric: str = "rel_l2_log_y") -> dict[str, float]:
    """``{strategy: mean of metric over all materials}``."""
    recs = [rec["scores"] for rec in result["materials"].values()]
    return {name: float(np.mean([s[name][metric] for s in recs])) for name in recs[0]}


def predicted_times(device: Device, sampling: dict[str, Any]) -> dict[str, Any]:
    """Predicted acquisition times (btfcore.acquisition.time_model) of the plans of the paper-4 strategies.

    On the evaluated device (its turntable positions) and on the thesis' full
    dome (12 positions, the thesis' n_s = 400 pairs drawn at random: the time
    depends on the count, not on which pairs).
    """
    from btfcore.acquisition.plan import full_single_light_plan, multiplexed_plan, sparse_multiplexed_plan, sparse_plan
    from btfcore.acquisition.time_model import predict_time

    p4 = sampling["paper4"]
    n400 = str(THESIS_N_S[-1])
    here = {
        "full-single": predict_time(full_single_light_plan(device)).total_s,
        "sparse": predict_time(sparse_plan(device, np.asarray(p4["counts"][n400]["pairs"]))).total_s,
        "multiplexed": predict_time(multiplexed_plan(device)).total_s,
        "sparse-multiplexed": predict_time(sparse_multiplexed_plan(
            device, np.asarray(p4["sparse_multiplexed"]["pairs"]))).total_s,
    }
    full = get_device("bonn-dome2")
    rng = np.random.default_rng(0)
    n_p = multiplexing_patterns(full.n_leds).shape[0]

    def draw(n_cols: int) -> np.ndarray:
        flat = np.sort(rng.choice(full.n_turn * n_cols, size=THESIS_N_S[-1], replace=False))
        return np.stack(np.divmod(flat, n_cols), axis=1)

    thesis = {
        "full-single": predict_time(full_single_light_plan(full)).total_s,
        "sparse": predict_time(sparse_plan(full, draw(full.n_leds))).total_s,
        "multiplexed": predict_time(multiplexed_plan(full)).total_s,
        "sparse-multiplexed": predict_time(sparse_multiplexed_plan(full, draw(n_p))).total_s,
    }
    return {"evaluated_device_s": here, "thesis_device_s": thesis,
            "exposure": "btfcore.acquisition.plan.ExposureModel() defaults: single-light bracket 10, 100, 1000 ms; a pattern "
                        "of m LEDs 1/m of it", "params": "btfcore.acquisition.time_model.TimeModelParams() defaults"}


def _verdict(ok: bool) -> str:
    return "met" if ok else "not met"


def _claim_a(cm: dict[str, dict[str, float]]) -> dict[str, Any]:
    rows = {cls: {k: round(100 * cm[cls][k], 3) for k in PAPER1_SAMPLED} for cls in STRUCTURED_CLASSES if cls in cm}
    ok = bool(rows) and all(r["abtf-optimized"] < r["abrdf-optimized"] and r["abtf-pmap7"] < r["abrdf-pmap7"]
                            for r in rows.values())
    return {"claim": "With about 6% of the samples, ABTF-patch reconstruction beats ABRDF reconstruction on "
                     "carpet, stone and leather (paper 1 Table 2), log Y relative L2 [%]",
            "numbers": rows, "rule": "ABTF < ABRDF for both samplings in every listed class",
            "verdict": _verdict(ok) if rows else "not tested (no structured class in the database)"}


def _claim_b(result: dict[str, Any], om: dict[str, float]) -> dict[str, Any]:
    per_mat = [rec["scores"] for rec in result["materials"].values()]
    nums = {}
    ok = True
    for model in ("abrdf", "abtf"):
        o, p = om[f"{model}-optimized"], om[f"{model}-pmap7"]
        wins = sum(s[f"{model}-optimized"]["rel_l2_log_y"] < s[f"{model}-pmap7"]["rel_l2_log_y"] for s in per_mat)
        nums[model] = {"optimized": round(100 * o, 3), "pmap7": round(100 * p, 3),
                       "materials_where_optimized_wins": f"{wins}/{len(per_mat)}"}
        ok = ok and o < p
    return {"claim": "Optimised sampling (random swap, paper 1 Alg. 1) beats the 7x7 parabolic map at the same "
                     "number of samples, mean log Y relative L2 [%] over all materials",
            "numbers": nums, "rule": "mean(optimized) < mean(pmap7) for ABRDF and ABTF bases",
            "verdict": _verdict(ok)}


def _claim_c(cm: dict[str, dict[str, float]], om: dict[str, float]) -> dict[str, Any]:
    rows: dict[str, Any] = {cls: {k: round(100 * cm[cls][k], 3) for k in VMV_DENOISING} for cls in cm}
    rows["all"] = {k: round(100 * om[k], 3) for k in VMV_DENOISING}
    a = rows["all"]
    classes = [r for k, r in rows.items() if k != "all"]
    rows["halves"] = {f"{lo} < {hi}": {"means": _verdict(a[lo] < a[hi]),
                                       "classes": f"{sum(r[lo] < r[hi] for r in classes)}/{len(classes)}"}
                      for lo, hi in (("projection", "demultiplexed"), ("thresholded", "projection"))}
    in_order = sum(r["thresholded"] < r["projection"] < r["demultiplexed"] for r in classes)
    return {"claim": "Thresholded de-noising beats projection de-noising, which beats plain demultiplexing "
                     "(VMV Table 1), log Y relative L2 [%]", "numbers": rows,
            "rule": "thresholded < projection < demultiplexed, means over all materials",
            "classes_in_order": f"{in_order}/{len(cm)}",
            "verdict": _verdict(a["thresholded"] < a["projection"] < a["demultiplexed"])}


def _claim_d(om: dict[str, float], times: dict[str, Any]) -> dict[str, Any]:
    n = THESIS_N_S[-1]
    e_sm, e_s, e_m = om[f"sparse-multiplexed-n{n}"], om[f"sparse-tikhonov-n{n}"], om["multiplexed-direct"]
    t = times["evaluated_device_s"]
    ok = e_sm <= 2 * e_s and e_sm <= 2 * e_m and t["sparse-multiplexed"] < min(t["sparse"], t["multiplexed"])
    return {"claim": f"Sparse + multiplexed with n_s = {n} of 2,376 (light, turntable) pairs (scaled to the "
                     "evaluated device), all cameras, has an error within 2x of sparse-only and of "
                     "multiplexed-only at a fraction of their predicted acquisition time (paper 4 §5.3)",
            "numbers": {"rel_l2_log_y_percent": {"sparse-multiplexed": round(100 * e_sm, 3),
                                                 "sparse-only (Tikhonov)": round(100 * e_s, 3),
                                                 "multiplexed-only (eq. 10)": round(100 * e_m, 3)},
                        "ratio_to_sparse": round(e_sm / e_s, 3), "ratio_to_multiplexed": round(e_sm / e_m, 3),
                        "predicted_time_s_evaluated_device": {k: round(v, 1) for k, v in t.items()},
                        "predicted_time_h_thesis_device": {k: round(v / 3600, 3)
                                                           for k, v in times["thesis_device_s"].items()}},
            "rule": "error <= 2x both, and predicted time < both (evaluated device)",
            "verdict": _verdict(ok)}


def _claim_e(om: dict[str, float]) -> dict[str, Any]:
    n0 = THESIS_N_S[0]
    tik, pinv = om[f"sparse-tikhonov-n{n0}"], om[f"sparse-pinv-n{n0}"]
    nums = {f"n_s={n_}": {"tikhonov": round(100 * om[f"sparse-tikhonov-n{n_}"], 3),
                          "pinv": round(100 * om[f"sparse-pinv-n{n_}"], 3)} for n_ in THESIS_N_S}
    return {"claim": f"Tikhonov with lambda*Sigma^-1 (lambda = {LAMBDA_ALS}, ALS basis) beats the unregularised "
                     "pseudo-inverse at the smallest sample count, mean log Y relative L2 [%] (thesis n_s scaled)",
            "numbers": nums, "rule": f"tikhonov < pinv at the thesis' n_s = {n0} (scaled)",
            "verdict": _verdict(tik < pinv)}


def claims(result: dict[str, Any], times: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The thesis' claims (a)-(e) with their numbers and a verdict computed from them.

    Parameters
    ----------
    result : dict
        Scores per material (module docstring).
    times : dict
        :func:`predicted_times`.

    Returns
    -------
    claims : dict
        ``{"a" ... "e": {"claim", "numbers", "rule", "verdict", ...}}``.
    """
    cm, om = class_means(result), overall_means(result)
    return {"a": _claim_a(cm), "b": _claim_b(result, om), "c": _claim_c(cm, om), "d": _claim_d(om, times),
            "e": _claim_e(om)}


def thesis_tables(result: dict[str, Any]) -> dict[str, Any]:
    """Tables shaped like the thesis': paper 1 Table 2, VMV Table 1 and every strategy (percent)."""
    cm = class_means(result)
    t2 = [["class", "ABRDF proj", "ABRDF pmap7", "ABRDF optimized", "ABTF proj", "ABTF pmap7", "ABTF optimized"]]
    for cls, row in cm.items():
        t2.append([cls] + [round(100 * row[k], 2) for k in ("abrdf-projection", "abrdf-pmap7", "abrdf-optimized",
                                                            "abtf-projection", "abtf-pmap7", "abtf-optimized")])
    t1 = [["material", "class", "eps_demult", "eps_denoised", "eps_threshold"]]
    for mid, rec in result["materials"].items():
        t1.append([mid, rec["class"]] + [round(100 * rec["scores"][k]["rel_l2_log_y"], 2) for k in VMV_DENOISING])
    for cls, row in cm.items():
        t1.append([f"mean {cls}", cls] + [round(100 * row[k], 2) for k in VMV_DENOISING])
    om = {m: overall_means(result, m) for m in ("rel_l2_log_y", "mrmse", "mpsnr", "mre")}
    t4 = [["strategy", "rel. L2 log Y [%]", "mRMSE", "mPSNR [dB]", "mRE [%]"]]
    for name in strategy_names():                                  # the registry's rows, in its order
        t4.append([name, round(100 * om["rel_l2_log_y"][name], 2), float(f"{om['mrmse'][name]:.4g}"),
                   round(om["mpsnr"][name], 2), round(om["mre"][name], 2)])
    return {"paper1_table2": t2, "vmv_table1": t1, "all_strategies": t4}
