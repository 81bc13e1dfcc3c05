"""The thesis' claims (a)-(e), issue 20's bar on basis-aware patterns (f) and the thesis' tables, computed from
the evaluation's scores.

Every verdict is computed from the numbers beside it by the rule it states,
never written by hand (docs/evaluation.md, "Claims and measured numbers").
``result`` is :func:`tasks.evaluate_acquisition.graph.evaluate_materials`'
``{"materials": {id: {"class": str, "scores": {strategy: {metric: float}}}}}``;
errors are fractions here and per cent in the claims.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from btfcore.acquisition.band_evaluation import conditioning, divergence
from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.reconstruct import LAMBDA_ALS
from btfcore.acquisition.strategies import (
    FLOOR_COMPUTED,
    FLOOR_EXACT,
    FLOOR_NOTES,
    THESIS_N_S,
    floor_kinds,
    strategy_names,
)
from btfcore.dome import Device, get_device
from tasks.evaluate_acquisition.config import STRUCTURED_CLASSES

#: The strategies of claims (a) and (b), paper 1 Table 2.
PAPER1_SAMPLED = ("abrdf-pmap7", "abrdf-optimized", "abtf-pmap7", "abtf-optimized")
#: The strategies of claim (c), VMV Table 1, in its order.
VMV_DENOISING = ("demultiplexed", "projection", "thresholded")


def result_flags(result: dict[str, Any]) -> dict[str, dict[str, dict[str, str]]]:
    """Every diverged and every ill-conditioned result, with its reason.

    Decided by :func:`btfcore.acquisition.band_evaluation.divergence` and
    :func:`~btfcore.acquisition.band_evaluation.conditioning` (docs/evaluation.md,
    "Diverged and ill-conditioned results"), from a material's scores and its
    strategies' ``info``.

    Returns
    -------
    flags : dict
        ``{"diverged": {material: {strategy: reason}}, "ill_conditioned": {material: {strategy: reason}}}``
        (materials without a flag left out).
    """
    out: dict[str, dict[str, dict[str, str]]] = {"diverged": {}, "ill_conditioned": {}}
    for mid, rec in result["materials"].items():
        for name, scores in rec["scores"].items():
            info = (rec.get("strategies") or {}).get(name) or {}
            for kind, reason in (("diverged", divergence(scores, info)), ("ill_conditioned", conditioning(info))):
                if reason:
                    out[kind].setdefault(mid, {})[name] = reason
    return out


def _diverged(rec: dict[str, Any], name: str) -> bool:
    return divergence(rec["scores"][name], (rec.get("strategies") or {}).get(name)) is not None


def mean_stats(result: dict[str, Any], metric: str = "rel_l2_log_y") -> dict[str, dict[str, tuple[float, int, int]]]:
    """``{group: {strategy: (mean, diverged left out, results)}}``, groups the classes and ``"all"``.

    The mean is over the results that have not diverged; where every result of
    a group has diverged it is over all of them (and says so: left out = results).
    """
    groups: dict[str, list[dict[str, Any]]] = {}
    for rec in result["materials"].values():
        groups.setdefault(rec["class"], []).append(rec)
    groups = {**dict(sorted(groups.items())), "all": list(result["materials"].values())}
    out: dict[str, dict[str, tuple[float, int, int]]] = {}
    for group, recs in groups.items():
        out[group] = {}
        for name in recs[0]["scores"]:
            kept = [r["scores"][name][metric] for r in recs if not _diverged(r, name)]
            every = [r["scores"][name][metric] for r in recs]
            out[group][name] = (float(np.mean(kept or every)), len(every) - len(kept), len(every))
    return out


def floor_result(result: dict[str, Any]) -> dict[str, Any]:
    """``result`` with each material's noise-free floors (``"floors"``) as its scores; materials without
    floors left out. Its :func:`mean_stats` are the floors' means, diverged floors left out alike."""
    return {"materials": {mid: {**rec, "scores": rec["floors"]} for mid, rec in result["materials"].items()
                          if rec.get("floors")}}


def floor_means(result: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per strategy its noise-free floor: the kind, what it is and, where computed, its means.

    Returns
    -------
    floors : dict
        ``{strategy: {"kind", "note"}}`` (kinds of :mod:`btfcore.acquisition.strategies`); a computed
        floor adds the means over the materials of ``rel_l2_log_y``, ``mrmse``, ``mpsnr``, ``mre`` (the
        scores' units) with diverged floors left out (:func:`mean_stats`), ``"diverged_left_out"``
        (``[left out, results]``) and ``"materials"`` (the materials with floors).
    """
    floors = floor_result(result)
    stats = {m: mean_stats(floors, m)["all"] for m in ("rel_l2_log_y", "mrmse", "mpsnr", "mre")} \
        if floors["materials"] else {}
    out: dict[str, dict[str, Any]] = {}
    for name, kind in floor_kinds().items():
        out[name] = {"kind": kind, "note": FLOOR_NOTES[kind]}
        if kind == FLOOR_COMPUTED and name in stats.get("rel_l2_log_y", {}):
            out[name].update({m: v[name][0] for m, v in stats.items()})
            out[name]["diverged_left_out"] = list(stats["rel_l2_log_y"][name][1:])
            out[name]["materials"] = sorted(floors["materials"])
    return out


def excluded_text(left_out: int, total: int) -> str | None:
    """How many diverged results a mean leaves out (None when none)."""
    if not left_out:
        return None
    if left_out == total:
        return f"all {total} results diverged: the mean is over them (docs/evaluation.md)"
    return f"{left_out} of {total} results diverged and are left out of this mean"


def class_means(result: dict[str, Any], metric: str = "rel_l2_log_y") -> dict[str, dict[str, float]]:
    """``{class: {strategy: mean of metric over the class' materials}}`` (errors in the metric's unit),
    diverged results left out (:func:`mean_stats`)."""
    return {cls: {name: v[0] for name, v in row.items()} for cls, row in mean_stats(result, metric).items()
            if cls != "all"}


def overall_means(result: dict[str, Any], metric: str = "rel_l2_log_y") -> dict[str, float]:
    """``{strategy: mean of metric over all materials}``, diverged results left out (:func:`mean_stats`)."""
    return {name: v[0] for name, v in mean_stats(result, metric)["all"].items()}


def _excluded(stats: dict[str, dict[str, tuple[float, int, int]]], names: Any) -> dict[str, dict[str, str]]:
    """``{group: {strategy: "left out of total"}}`` of ``names`` where a mean leaves diverged results out."""
    out = {g: {n: f"{row[n][1]} of {row[n][2]}" for n in names if n in row and row[n][1]} for g, row in stats.items()}
    return {g: row for g, row in out.items() if row}


def _cell(stats: dict[str, dict[str, tuple[float, int, int]]], group: str, name: str, scale: float = 100.0,
          digits: int = 3) -> Any:
    """A mean as a table cell: the number, or ``{"value", "flag"}`` when it leaves diverged results out."""
    mean, left_out, total = stats[group][name]
    value = round(scale * mean, digits)
    reason = excluded_text(left_out, total)
    return {"value": value, "flag": reason} if reason else value


def predicted_times(device: Device, sampling: dict[str, Any]) -> dict[str, Any]:
    """Predicted acquisition times (btfcore.acquisition.time_model) of the plans of the paper-4 strategies.

    On the evaluated device (its turntable positions) and on the thesis' full
    dome (12 positions, the thesis' n_s = 400 pairs drawn at random: the time
    depends on the count, not on which pairs).
    """
    from btfcore.acquisition.plan import (full_single_light_plan, multiplexed_plan, patterns_plan,
                                          sparse_multiplexed_plan, sparse_plan)
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
    designed = {name: _patterns_matrix(sampling["patterns"][kind]["leds"], device.n_leds)
                for name, kind in PATTERN_PLANS.items() if "patterns" in sampling}
    here.update({name: predict_time(patterns_plan(device, p)).total_s for name, p in designed.items()})
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
    thesis.update({name: predict_time(patterns_plan(full, p)).total_s for name, p in designed.items()
                   if p.shape[1] == full.n_leds})
    return {"evaluated_device_s": here, "thesis_device_s": thesis,
            "exposure": "btfcore.acquisition.plan.ExposureModel() defaults: single-light bracket 10, 100, 1000 ms; a pattern "
                        "of m LEDs 1/m of it", "params": "btfcore.acquisition.time_model.TimeModelParams() defaults"}


#: The plans of the pattern strategies (issue 20) in :func:`predicted_times`: their patterns in the sampling report.
PATTERN_PLANS = {"patterns": "designed", "smatrix-subsampled": "subsampled"}


def _patterns_matrix(leds: list[list[int]], n_leds: int) -> np.ndarray:
    p = np.zeros((len(leds), n_leds), dtype=np.uint8)
    for i, on in enumerate(leds):
        p[i, on] = 1
    return p


def _verdict(ok: bool) -> str:
    return "met" if ok else "not met"


def _pct(x: float) -> str:
    return f"{x:.3g} %"


def _claim_a(st: dict[str, dict[str, tuple[float, int, int]]]) -> dict[str, Any]:
    classes = [cls for cls in STRUCTURED_CLASSES if cls in st]
    rows = {cls: {k: round(100 * st[cls][k][0], 3) for k in PAPER1_SAMPLED} for cls in classes}
    ok_classes = [cls for cls, r in rows.items()
                  if r["abtf-optimized"] < r["abrdf-optimized"] and r["abtf-pmap7"] < r["abrdf-pmap7"]]
    ok = bool(rows) and len(ok_classes) == len(rows)
    measured = (f"ABTF below ABRDF with both samplings in {len(ok_classes)} of {len(rows)} structured classes; "
                + "; ".join(f"{cls}: ABTF {_pct(r['abtf-optimized'])} vs ABRDF {_pct(r['abrdf-optimized'])} "
                            f"(optimized), {_pct(r['abtf-pmap7'])} vs {_pct(r['abrdf-pmap7'])} (pmap7)"
                            for cls, r in rows.items())) if rows else "no structured class in the database"
    table = [["class"] + [f"{k} [%]" for k in PAPER1_SAMPLED]] + [
        [cls] + [_cell(st, cls, k) for k in PAPER1_SAMPLED] for cls in classes]
    return {"claim": "With about 6% of the samples, ABTF-patch reconstruction beats ABRDF reconstruction on "
                     "carpet, stone and leather (paper 1 Table 2), log Y relative L2 [%]",
            "numbers": rows, "rule": "ABTF < ABRDF for both samplings in every listed class",
            "verdict": _verdict(ok) if rows else "not tested (no structured class in the database)",
            "measured": measured, "excluded": _excluded({c: st[c] for c in classes}, PAPER1_SAMPLED),
            "tables": [{"caption": "class means of the log Y relative L2 error", "rows": table}] if rows else []}


def _claim_b(result: dict[str, Any], st: dict[str, dict[str, tuple[float, int, int]]]) -> dict[str, Any]:
    recs = list(result["materials"].values())
    nums = {}
    ok = True

    def error(rec: dict[str, Any], name: str) -> tuple[bool, float]:   # a diverged result loses to one that is not
        return _diverged(rec, name), rec["scores"][name]["rel_l2_log_y"]

    for model in ("abrdf", "abtf"):
        o, p = st["all"][f"{model}-optimized"][0], st["all"][f"{model}-pmap7"][0]
        wins = sum(error(r, f"{model}-optimized") < error(r, f"{model}-pmap7") for r in recs)
        nums[model] = {"optimized": round(100 * o, 3), "pmap7": round(100 * p, 3),
                       "materials_where_optimized_wins": f"{wins}/{len(recs)}"}
        ok = ok and o < p
    names = [f"{m}-{s}" for m in ("abrdf", "abtf") for s in ("optimized", "pmap7")]
    table = [["basis", "optimized [%]", "pmap7 [%]", "materials where optimized wins"]] + [
        [model.upper(), _cell(st, "all", f"{model}-optimized"), _cell(st, "all", f"{model}-pmap7"),
         nums[model]["materials_where_optimized_wins"]] for model in ("abrdf", "abtf")]
    return {"claim": "Optimised sampling (random swap, paper 1 Alg. 1) beats the 7x7 parabolic map at the same "
                     "number of samples, mean log Y relative L2 [%] over all materials",
            "numbers": nums, "rule": "mean(optimized) < mean(pmap7) for ABRDF and ABTF bases",
            "verdict": _verdict(ok),
            "measured": "; ".join(f"{m.upper()}: optimized {_pct(n['optimized'])} vs pmap7 {_pct(n['pmap7'])}, "
                                  f"optimized better on {n['materials_where_optimized_wins']} materials"
                                  for m, n in nums.items()),
            "excluded": _excluded({"all": st["all"]}, names),
            "tables": [{"caption": "mean log Y relative L2 error over all materials", "rows": table}]}


def _claim_c(st: dict[str, dict[str, tuple[float, int, int]]]) -> dict[str, Any]:
    rows: dict[str, Any] = {cls: {k: round(100 * st[cls][k][0], 3) for k in VMV_DENOISING} for cls in st}
    a = rows["all"]
    classes = [r for k, r in rows.items() if k != "all"]
    rows["halves"] = {f"{lo} < {hi}": {"means": _verdict(a[lo] < a[hi]),
                                       "classes": f"{sum(r[lo] < r[hi] for r in classes)}/{len(classes)}"}
                      for lo, hi in (("projection", "demultiplexed"), ("thresholded", "projection"))}
    in_order = sum(r["thresholded"] < r["projection"] < r["demultiplexed"] for r in classes)
    table = [["class"] + [f"{k} [%]" for k in VMV_DENOISING] + ["thresholded < projection < demultiplexed"]] + [
        [cls] + [_cell(st, cls, k) for k in VMV_DENOISING]
        + [_yes(rows[cls]["thresholded"] < rows[cls]["projection"] < rows[cls]["demultiplexed"])] for cls in st]
    halves = [["comparison", "over the means of all materials", "classes where it holds"]] + [
        [name, h["means"], h["classes"]] for name, h in rows["halves"].items()]
    return {"claim": "Thresholded de-noising beats projection de-noising, which beats plain demultiplexing "
                     "(VMV Table 1), log Y relative L2 [%]", "numbers": rows,
            "rule": "thresholded < projection < demultiplexed, means over all materials",
            "classes_in_order": f"{in_order}/{len(classes)}",
            "verdict": _verdict(a["thresholded"] < a["projection"] < a["demultiplexed"]),
            "measured": f"over all materials thresholded {_pct(a['thresholded'])}, projection "
                        f"{_pct(a['projection'])}, demultiplexed {_pct(a['demultiplexed'])}; in this order in "
                        f"{in_order} of {len(classes)} classes",
            "excluded": _excluded(st, VMV_DENOISING),
            "tables": [{"caption": "means of the log Y relative L2 error ('all': over all materials)", "rows": table},
                       {"caption": "each half of the claim", "rows": halves}]}


def _yes(ok: bool) -> str:
    return "yes" if ok else "no"


def _claim_d(st: dict[str, dict[str, tuple[float, int, int]]], times: dict[str, Any]) -> dict[str, Any]:
    n = THESIS_N_S[-1]
    names = {"sparse-multiplexed": f"sparse-multiplexed-n{n}", "sparse": f"sparse-tikhonov-n{n}",
             "multiplexed": "multiplexed-direct"}
    e_sm, e_s, e_m = (st["all"][names[k]][0] for k in ("sparse-multiplexed", "sparse", "multiplexed"))
    t = times["evaluated_device_s"]
    ok = e_sm <= 2 * e_s and e_sm <= 2 * e_m and t["sparse-multiplexed"] < min(t["sparse"], t["multiplexed"])
    labels = {"sparse-multiplexed": "sparse + multiplexed", "sparse": "sparse-only (Tikhonov)",
              "multiplexed": "multiplexed-only (eq. 10)", "full-single": "full single-light"}
    table = [["acquisition", "log Y rel. L2 [%]", "sparse + multiplexed error over this one [1]",
              "predicted time, evaluated device [s]", "predicted time, thesis device [h]"]] + [
        [labels[k], _cell(st, "all", names[k]) if k in names else None,
         round(e_sm / st["all"][names[k]][0], 3) if k in names else None,
         round(t[k], 1), round(times["thesis_device_s"][k] / 3600, 3)] for k in labels if k in t]
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
            "verdict": _verdict(ok),
            "measured": f"sparse + multiplexed {_pct(100 * e_sm)}: {e_sm / e_s:.3g}x sparse-only "
                        f"({_pct(100 * e_s)}) and {e_sm / e_m:.3g}x multiplexed-only ({_pct(100 * e_m)}); "
                        f"predicted {t['sparse-multiplexed']:,.0f} s against {t['sparse']:,.0f} s and "
                        f"{t['multiplexed']:,.0f} s",
            "excluded": _excluded({"all": st["all"]}, names.values()),
            "tables": [{"caption": "means over all materials; times by btfcore.acquisition.time_model",
                        "rows": table}]}


def _claim_e(result: dict[str, Any], st: dict[str, dict[str, tuple[float, int, int]]]) -> dict[str, Any]:
    n0 = THESIS_N_S[0]
    om = {name: v[0] for name, v in st["all"].items()}
    tik, pinv = om[f"sparse-tikhonov-n{n0}"], om[f"sparse-pinv-n{n0}"]
    nums = {f"n_s={n_}": {"tikhonov": round(100 * om[f"sparse-tikhonov-n{n_}"], 3),
                          "pinv": round(100 * om[f"sparse-pinv-n{n_}"], 3)} for n_ in THESIS_N_S}
    info = (next(iter(result["materials"].values())).get("strategies") or {})
    table = [["n_s (thesis)", "n_s (evaluated device)", "Tikhonov [%]", "pinv [%]"]] + [
        [n_, (info.get(f"sparse-pinv-n{n_}") or {}).get("n_s"), _cell(st, "all", f"sparse-tikhonov-n{n_}"),
         _cell(st, "all", f"sparse-pinv-n{n_}")] for n_ in THESIS_N_S]
    return {"claim": f"Tikhonov with lambda*Sigma^-1 (lambda = {LAMBDA_ALS}, ALS basis) beats the unregularised "
                     "pseudo-inverse at the smallest sample count, mean log Y relative L2 [%] (thesis n_s scaled)",
            "numbers": nums, "rule": f"tikhonov < pinv at the thesis' n_s = {n0} (scaled)",
            "verdict": _verdict(tik < pinv),
            "measured": f"at the thesis' n_s = {n0}: Tikhonov {_pct(100 * tik)} vs pinv {_pct(100 * pinv)}",
            "excluded": _excluded({"all": st["all"]}, [f"sparse-{k}-n{n_}" for n_ in THESIS_N_S
                                                       for k in ("tikhonov", "pinv")]),
            "tables": [{"caption": "mean log Y relative L2 error over all materials", "rows": table}]}


def _claim_f(result: dict[str, Any], st: dict[str, dict[str, tuple[float, int, int]]],
             times: dict[str, Any]) -> dict[str, Any]:
    """Issue 20's bar: m <= n/4 basis-aware patterns, error no worse than the full S-matrix's at no more than
    half its predicted time."""
    names = {"patterns": "patterns-quarter", "smatrix-subsampled": "smatrix-quarter",
             "multiplexed": "multiplexed-direct"}
    t = times["evaluated_device_s"]
    if not all(n in st["all"] for n in names.values()) or "patterns" not in t:
        return {"claim": "issue 20: basis-aware patterns", "rule": "-", "verdict": "not tested (no pattern "
                "strategies in these results)", "measured": "", "numbers": {}, "excluded": {}, "tables": []}
    rec = next(iter(result["materials"].values()))
    info = (rec.get("strategies") or {}).get("patterns-quarter") or {}
    pred = ((rec.get("sampling") or {}).get("patterns") or {})
    m, n = info.get("m"), pred.get("n_leds")
    e = {k: st["all"][v][0] for k, v in names.items()}
    ratio_t = t["patterns"] / t["multiplexed"]
    ok = e["patterns"] <= e["multiplexed"] and ratio_t <= 0.5 and m is not None and n is not None and 4 * m <= n
    classes = [c for c in st if c != "all"]
    wins = sum(st[c][names["patterns"]][0] <= st[c][names["multiplexed"]][0] for c in classes)
    labels = {"patterns": f"basis-aware patterns (m = {m})", "smatrix-subsampled": f"S-matrix rows (m = {m})",
              "multiplexed": "full S-matrix (multiplexed-direct)"}
    table = [["acquisition", "log Y rel. L2 [%]", "error over the full S-matrix's [1]",
              "predicted time, evaluated device [s]", "time over the full S-matrix's [1]",
              "predicted time, thesis device [h]"]] + [
        [labels[k], _cell(st, "all", names[k]), round(e[k] / e["multiplexed"], 3), round(t[k], 1),
         round(t[k] / t["multiplexed"], 3),
         round(times["thesis_device_s"][k] / 3600, 3) if k in times["thesis_device_s"] else None] for k in labels]
    per_class = [["class"] + [f"{names[k]} [%]" for k in labels]] + [
        [c] + [_cell(st, c, names[k]) for k in labels] for c in classes]
    return {"claim": f"issue 20: with m <= n/4 basis-aware binary LED patterns (m = {m} of n = {n} LEDs), the "
                     "reconstruction error is no worse than the full S-matrix's with all its patterns, at no more "
                     "than half its predicted acquisition time",
            "numbers": {"rel_l2_log_y_percent": {k: round(100 * v, 3) for k, v in e.items()},
                        "time_ratio_to_full_s_matrix": round(ratio_t, 3),
                        "predicted_time_s_evaluated_device": {k: round(t[k], 1) for k in labels},
                        "predicted_relative_error_noise_only": pred.get("predicted_relative_error"),
                        "classes_where_patterns_no_worse": f"{wins}/{len(classes)}"},
            "rule": "mean error(patterns) <= mean error(full S-matrix), predicted time <= 0.5 x, and 4 m <= n",
            "verdict": _verdict(ok),
            "measured": f"patterns {_pct(100 * e['patterns'])} vs full S-matrix {_pct(100 * e['multiplexed'])} "
                        f"(S-matrix rows at the same m {_pct(100 * e['smatrix-subsampled'])}); predicted "
                        f"{t['patterns']:,.0f} s vs {t['multiplexed']:,.0f} s ({ratio_t:.3g}x); no worse in "
                        f"{wins} of {len(classes)} classes",
            "excluded": _excluded({"all": st["all"]}, names.values()),
            "tables": [{"caption": "means over all materials; times by btfcore.acquisition.time_model", "rows": table},
                       {"caption": "class means of the log Y relative L2 error", "rows": per_class}]}


def claims(result: dict[str, Any], times: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The thesis' claims (a)-(e) and issue 20's pattern bar (f) with their numbers and a verdict computed from them.

    Means leave diverged results out (:func:`mean_stats`); ``excluded`` says how many.

    Parameters
    ----------
    result : dict
        Scores per material (module docstring).
    times : dict
        :func:`predicted_times`.

    Returns
    -------
    claims : dict
        ``{"a" ... "f": {"claim", "numbers", "rule", "verdict", "measured", "excluded", "tables", ...}}``:
        ``claim`` what the thesis claims, ``measured`` a sentence of what was measured, ``excluded``
        ``{group: {strategy: "n of m"}}`` the diverged results left out of a mean, ``tables`` its numbers as
        ``[{"caption", "rows"}]`` (header first, units in brackets; a cell ``{"value", "flag"}`` is flagged).
    """
    st = mean_stats(result)
    return {"a": _claim_a(st), "b": _claim_b(result, st), "c": _claim_c(st), "d": _claim_d(st, times),
            "e": _claim_e(result, st), "f": _claim_f(result, st, times)}


def thesis_tables(result: dict[str, Any], flagged: bool = False) -> dict[str, Any]:
    """Tables shaped like the thesis': paper 1 Table 2, VMV Table 1 and every strategy, and the flagged results.

    Each a list of rows, the header first with each column's unit in brackets.
    Means leave diverged results out (:func:`mean_stats`). The every-strategy table has each
    strategy's noise-free floor beside its error (:func:`floor_means`). With ``flagged`` a
    cell that is a mean leaving results out, or a diverged or ill-conditioned
    result, is ``{"value", "flag": reason}`` (for the HTML report;
    :mod:`tasks.html_report` draws it in red).
    """
    st = {m: mean_stats(result, m) for m in ("rel_l2_log_y", "mrmse", "mpsnr", "mre")}
    flags = result_flags(result)

    def mean(metric: str, group: str, name: str, scale: float = 100.0, digits: int = 2) -> Any:
        cell = _cell(st[metric], group, name, scale, digits)
        return cell if flagged or not isinstance(cell, dict) else cell["value"]

    def own(mid: str, name: str, value: float) -> Any:
        reason = flags["diverged"].get(mid, {}).get(name) or flags["ill_conditioned"].get(mid, {}).get(name)
        return {"value": value, "flag": reason} if flagged and reason else value

    classes = [c for c in st["rel_l2_log_y"] if c != "all"]
    p1 = ("abrdf-projection", "abrdf-pmap7", "abrdf-optimized", "abtf-projection", "abtf-pmap7", "abtf-optimized")
    t2 = [["class", "ABRDF proj [%]", "ABRDF pmap7 [%]", "ABRDF optimized [%]", "ABTF proj [%]", "ABTF pmap7 [%]",
           "ABTF optimized [%]"]]
    t2 += [[cls] + [mean("rel_l2_log_y", cls, k) for k in p1] for cls in classes]
    t1 = [["material", "class", "eps_demult [%]", "eps_denoised [%]", "eps_threshold [%]"]]
    for mid, rec in result["materials"].items():
        t1.append([mid, rec["class"]] + [own(mid, k, round(100 * rec["scores"][k]["rel_l2_log_y"], 2))
                                         for k in VMV_DENOISING])
    t1 += [[f"mean {cls}", cls] + [mean("rel_l2_log_y", cls, k) for k in VMV_DENOISING] for cls in classes]
    floors = floor_result(result)
    floor_st = mean_stats(floors) if floors["materials"] else {"all": {}}
    kinds = floor_kinds()

    def floor(name: str) -> Any:
        if name in floor_st["all"]:
            cell = _cell(floor_st, "all", name, 100.0, 2)
            return cell if flagged or not isinstance(cell, dict) else cell["value"]
        return {FLOOR_EXACT: "0 (exact)", FLOOR_COMPUTED: None}.get(kinds[name], "its own error (reads the truth)")

    t4 = [["strategy", "rel. L2 log Y [%]", "noise-free floor, rel. L2 log Y [%]", "mRMSE [linear BTF units]",
           "mPSNR [dB]", "mRE [%]", "diverged results left out"]]
    for name in strategy_names():                                  # the registry's rows, in its order
        _, left_out, total = st["rel_l2_log_y"]["all"][name]
        t4.append([name, mean("rel_l2_log_y", "all", name), floor(name), mean("mrmse", "all", name, 1.0, 6),
                   mean("mpsnr", "all", name, 1.0), mean("mre", "all", name, 1.0),
                   f"{left_out} of {total}" if left_out else "none"])
    bad = [["material", "strategy", "rel. L2 log Y [%]", "mPSNR [dB]", "mRE [%]", "condition number [1]",
            "basis vectors", "samples", "reason"]]
    for kind in ("diverged", "ill_conditioned"):
        for mid, names in flags[kind].items():
            rec = result["materials"][mid]
            for name, reason in names.items():
                s, info = rec["scores"][name], (rec.get("strategies") or {}).get(name) or {}
                cond = info.get("kappa_log_y", info.get("condition"))
                bad.append([mid, name, own(mid, name, round(100 * s["rel_l2_log_y"], 2)), round(s["mpsnr"], 2),
                            float(f"{s['mre']:.4g}"), None if cond is None else float(f"{cond:.3g}"),
                            info.get("k"), info.get("n_meas"), reason])
    return {"paper1_table2": t2, "vmv_table1": t1, "all_strategies": t4, "flagged_results": bad}
