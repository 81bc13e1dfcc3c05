"""Issue 20 study (not a speed benchmark): probe groups and four survey estimators of the unmeasured rows' error.

The predictor's misfit comes from the start design's rows, which are not a sample of the rows the loop leaves
unmeasured (docs/adaptive-capture.md, "A second draw of materials"). This replays the evaluation's adaptive loops
(``study_adaptive_predictor``'s replay: the same bases, committee, simulator seeds and budget) with the loop's
``predictor='probes'`` (:func:`btfcore.acquisition.adaptive.run_adaptive`): every ``--every``-th step after the
start design is a **probe**, a group drawn uniformly from the unmeasured ones of a brightness stratum in turn,
which the committee's choice does not see, so that a probe's leave-one-group-out error is distributed as an
unmeasured group's of its stratum.

At every step it records the loop's posterior prediction (``predicted``) and the predictions of the four
estimates of :meth:`~btfcore.acquisition.adaptive.AdaptiveState.probe_estimates` (``mean``, ``ratio``, ``greg`` and
``stratified``, the loop's), the fused measured rows' predicted error added as the predictor adds it. It prints the
issue's bar 1 (the probes cost shots) and bar 2 at the budget's stop and the target stops
(``tasks.adaptive.adaptive_bars``) with each estimate as the prediction from ``PROBE_MIN`` probes on (the
posterior's before; a target tested from the loop's ``first_stop`` on). About 45 s per material at the default
scale on one core, 2 minutes at four turntable positions (docs/adaptive-capture.md, "Probe groups"). Its replay
of a material gives the evaluation's record of a ``--adaptive-predictor probes`` run (``stratified`` equals its
``predicted_probes``).

    .venv/bin/python benchmarks/study_adaptive_probes.py --db acq-db-s1 --eval out-s1 --seed 1 [--every 3]
"""

from __future__ import annotations

import copy
import dataclasses
import json
from typing import Any

import numpy as np

from btfcore.acquisition import adaptive as AD
from btfcore.acquisition.adaptive import FUSE_S2_FLOOR, LOG_YUV_EPS, PROBE_MIN, REC709_LUMA, fused_error
from study_adaptive_predictor import replay_held_out, replay_materials, replay_parser
from tasks import adaptive as TA

ESTIMATES = ("mean", "ratio", "greg", "stratified")


def _recording(log: list[dict[str, Any]], truth: dict[str, np.ndarray]):
    """``AdaptiveState.predict`` that appends each step's probe count and the four estimates' predictions to
    ``log`` (the truth is scored by the loop itself)."""
    predict = AD.AdaptiveState.predict

    def wrapped(self: AD.AdaptiveState, model: dict | None = None) -> dict[str, float]:
        m = model or self._model()
        out = predict(self, m)
        rec: dict[str, Any] = {"n_probes": len(self.probes)}
        if len(self.probes) >= PROBE_MIN:
            Yhat = m["Yhat"]
            measured = float(np.sum(fused_error(Yhat[self.rows], self.y @ REC709_LUMA, self.gain, self.noise,
                                                max(float(m["s2"]), FUSE_S2_FLOOR))))
            ss = float(np.sum(np.log(np.maximum(Yhat, LOG_YUV_EPS)) ** 2))
            rec.update({k: float(np.sqrt((measured + v * len(self.sub)) / ss))
                        for k, v in self.probe_estimates(m).items()})
        log.append(rec)
        return out
    return wrapped


def _as_prediction(records: dict[str, Any], name: str) -> dict[str, Any]:
    """The records with estimate ``name`` as the probes' prediction (the posterior's before ``PROBE_MIN`` probes;
    a target tested from :func:`~btfcore.acquisition.adaptive.first_stop` on), or, for ``predicted``, judged
    as a posterior loop's (a target tested from the start design on)."""
    out = copy.deepcopy(records)
    for rec in out.values():
        if name == "predicted":
            rec["settings"]["predictor"] = "posterior"
        for step in rec["steps"]:
            step["predicted_probes"] = step.get(name, step["predicted"])
    return out


def main() -> None:
    p = replay_parser(__doc__)
    p.add_argument("--every", type=int, default=AD.PROBE_EVERY, help="a probe every this many steps after the "
                                                                      "start design")
    a = p.parse_args()
    config, materials, chosen = replay_materials(a)
    config = dataclasses.replace(config, adaptive_predictor="probes")
    AD.PROBE_EVERY = a.every
    records = {}
    for m in chosen:
        records[m.material_id] = rec = replay_held_out(a.eval, config, m.material_id, materials, _recording)
        last = rec["steps"][-1]
        print(f"{m.material_id} at {last['n_shots']} shots ({last['n_probes']} probes): true {last['true']:.4f}; "
              "over the truth: " + ", ".join(f"{k} {last[k] / last['true']:.2f}" for k in ("predicted", *ESTIMATES)
                                             if k in last), flush=True)
    bars = TA.adaptive_bars(records)
    print("bar 1 (shots to the fixed n_s = 400 error, ratio):",
          json.dumps({c: round(v["ratio"], 2) for c, v in bars["shots_to_fixed_n400"].items()}))
    for name in ("predicted", *ESTIMATES):
        b = TA.adaptive_bars(_as_prediction(records, name))
        print(f"bar 2, {name}: within 25 % at the budget {b['share_within_25pct_stop']:.2f}, at the target "
              "stops " + ", ".join(f"{t['share_within_25pct']:.2f}" for t in b["at_target_stop"].values()))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(records, f)


if __name__ == "__main__":
    main()
