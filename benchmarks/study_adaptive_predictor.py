"""Issue 20 study (not a speed benchmark): where the adaptive loop's predicted error parts from the true error.

Replays the evaluation's adaptive loop of each held-out material in this process (the bases, simulator seeds,
noise and budget of ``tasks.adaptive._adaptive_task``, read from a finished ``btf evaluate acquisition`` output)
with :meth:`~btfcore.acquisition.adaptive.AdaptiveState.predict` wrapped, and records at every step:

- the prediction and the predictor's misfit ``s2_pred`` (and the fusion's ``s2``);
- the truth's squared log-Y error split into the measured rows' and the unmeasured rows' (both relative to
  the truth's ``sum log^2 Y``, on every texel), and the unmeasured entries' mean squared log error;
- the tail of the start rows' squared log residuals (well-exposed entries, the predictor's texels): the
  shares of their sum held by the largest 1 % and 10 % of the entries, and the fit over the measurement at
  the largest 1 % (median).

It prints, per material, these at a few steps, and the share of materials whose prediction is within 25 % of the
truth at the budget's stop and at the target stops (``tasks.adaptive.adaptive_bars``, as the evaluation's
report). The choice of groups does not use the prediction, so a variant of the predictor can be scored on the
same records (docs/adaptive-capture.md, "A second draw of materials"). About 20 s per material
at the default scale on one core.

    .venv/bin/python benchmarks/study_adaptive_predictor.py --db acq-db-s1 --eval out-s1 --seed 1 \\
        [--materials-per-class 2] [--materials 000-leather,003-metal] [--out predictor.json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from typing import Any

import numpy as np

from btfcore.acquisition import adaptive as AD
from btfcore.acquisition.adaptive import NOISE_MASK, luminance_noise
from btfcore.model.colour import LOG_YUV_EPS, REC709_LUMA
from tasks import adaptive as TA
from tasks.evaluate_acquisition.config import EvaluationConfig
from tasks.model import discover

def _tail(state: AD.AdaptiveState, m: dict[str, Any]) -> dict[str, float]:
    """The start rows' squared log residuals (well-exposed entries): their largest entries' share of the sum."""
    n0 = state.unbiased_groups * state.geometry.n_cam
    ys = (state.y @ REC709_LUMA)[:n0]
    v = luminance_noise(state.y, state.gain, state.noise)[:n0]
    good = v / np.maximum(ys, LOG_YUV_EPS) ** 2 < NOISE_MASK ** 2
    e2 = (m["e"][:n0] ** 2)[good]
    order = np.argsort(e2)[::-1]
    top1, top10 = order[:max(1, len(e2) // 100)], order[:max(1, len(e2) // 10)]
    fit = m["Yhat"][state.rows[:n0]][good]
    return {"top1pct_share": float(e2[top1].sum() / e2.sum()), "top10pct_share": float(e2[top10].sum() / e2.sum()),
            "top1pct_fit_over_measured": float(np.median(fit[top1] / np.maximum(ys[good][top1], 1e-12)))}


def _log_y(rgb: np.ndarray) -> np.ndarray:
    """log Y of linear RGB ``(..., 3)`` with the loop's luminance (Rec. 709, ``tasks.adaptive.truth_score``)."""
    return np.log(np.maximum(TA._luma(rgb), LOG_YUV_EPS))


def _recording(log: list[dict[str, Any]], truth: dict[str, np.ndarray]):
    """``AdaptiveState.predict`` that appends each step's parts to ``log`` (``truth['log_y']``: the held-out
    material's log Y, ``(n_lv, n_tx)``)."""
    predict = AD.AdaptiveState.predict

    def wrapped(self: AD.AdaptiveState, model: dict | None = None) -> dict[str, float]:
        m = model or self._model()
        out = predict(self, m)
        d2 = (_log_y(self.reconstruction(m)) - truth["log_y"]) ** 2
        measured = np.zeros(self.n_lv, dtype=bool)
        measured[self.rows] = True
        ss = float(np.sum(truth["log_y"] ** 2))
        rec = {"predicted": out["posterior"], "s2_pred": float(m["s2_pred"]), "s2": float(m["s2"]),
               "true_measured": float(d2[measured].sum() / ss), "true_unmeasured": float(d2[~measured].sum() / ss),
               "true_unmeasured_mean": float(d2[~measured].mean())}
        if self.unbiased_groups and len(self.groups) >= self.unbiased_groups:
            rec.update(_tail(self, m))
        log.append(rec)
        return out
    return wrapped


def replay_held_out(eval_dir: str, config: EvaluationConfig, material_id: str, materials: list[Any],
              recording=_recording) -> dict[str, Any]:
    """The evaluation's loop of one held-out material with ``recording(log, truth)`` as ``AdaptiveState.predict``
    (each call appends one record to ``log``; ``truth['log_y']`` the material's log Y): the evaluation's
    record, each step's entries joined by the step's recorded ones."""
    log: list[dict[str, Any]] = []
    truth_log_y: dict[str, np.ndarray] = {}
    keep = AD.AdaptiveState.predict, TA.adaptive_material
    adaptive_material = TA.adaptive_material

    def capture_truth(U, sigma, geometry, truth, *args, **kwargs):
        truth_log_y["log_y"] = _log_y(truth).reshape(len(truth), -1)
        return adaptive_material(U, sigma, geometry, truth, *args, **kwargs)

    AD.AdaptiveState.predict, TA.adaptive_material = recording(log, truth_log_y), capture_truth
    try:
        with tempfile.TemporaryDirectory() as scratch:
            rec = TA._adaptive_task(f"{eval_dir}/model.zarr", materials, material_id, config.model_settings(), config,
                                    None, f"{scratch}/record.json", "study")
    finally:
        AD.AdaptiveState.predict, TA.adaptive_material = keep
    return {"class": rec["class"], "n_shots": rec["n_shots"], "settings": rec["settings"], "fixed": rec["fixed"],
            "steps": [dict(s, **{k: v for k, v in r.items() if k != "predicted"}) for s, r in zip(rec["steps"], log)]}


def replay_parser(doc: str) -> argparse.ArgumentParser:
    """The replay's command line (a study adds its own options): the evaluation's database, output and seed."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("--db", required=True, help="the evaluation's truth database (--db of btf evaluate acquisition)")
    p.add_argument("--eval", required=True, help="its output folder (holds model.zarr)")
    p.add_argument("--seed", type=int, default=0, help="the evaluation's --eval-seed")
    p.add_argument("--materials-per-class", type=int, default=2)
    p.add_argument("--turntable", type=int, default=EvaluationConfig.n_turntable,
                   help="the evaluation's --eval-turntable")
    p.add_argument("--materials", default="", help="comma-separated material ids (default: all)")
    p.add_argument("--out", default="", help="JSON of every step's record")
    return p


def replay_materials(a: argparse.Namespace) -> tuple[EvaluationConfig, list[Any], list[Any]]:
    """The evaluation's configuration, its materials and those to replay (``--materials``, default all)."""
    materials = discover(a.db)
    only = set(filter(None, a.materials.split(",")))
    return (EvaluationConfig(materials_per_class=a.materials_per_class, seed=a.seed, n_turntable=a.turntable),
            materials,
            [m for m in materials if not only or m.material_id in only])


def main() -> None:
    a = replay_parser(__doc__).parse_args()
    config, materials, chosen = replay_materials(a)
    records = {}
    for m in chosen:
        records[m.material_id] = rec = replay_held_out(a.eval, config, m.material_id, materials)
        print(m.material_id, rec["class"], flush=True)
        for i in sorted({rec["settings"]["n_start"] - 1, 19, len(rec["steps"]) - 1}):
            s = rec["steps"][i]
            print(f"  {s['n_shots']:3d} shots: predicted {s['predicted']:.3f} true {s['true']:.3f} | s2_pred "
                  f"{s['s2_pred']:.4f}, unmeasured mean {s['true_unmeasured_mean']:.4f} | largest 1 % / 10 % of the "
                  f"start rows' squared log residuals: {s.get('top1pct_share', float('nan')):.2f} / "
                  f"{s.get('top10pct_share', float('nan')):.2f}, fit/measured "
                  f"{s.get('top1pct_fit_over_measured', float('nan')):.3f}", flush=True)
    bars = TA.adaptive_bars(records)        # the evaluation's bar 2: at the budget's stop and at the target stops
    print(json.dumps({"materials": len(records), "within_25pct": {
        "budget": bars["share_within_25pct"]["posterior"],
        **{n: t["share_within_25pct"] for n, t in bars["at_target_stop"].items()}}}))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(records, f)


if __name__ == "__main__":
    main()
