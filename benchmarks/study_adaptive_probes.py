"""Issue 20 study (not a speed benchmark): random probe groups and survey estimators of the unmeasured rows' error.

The predictor's misfit comes from the start design's rows, which are not a sample of the rows the loop leaves
unmeasured (docs/adaptive-capture.md, "A second draw of materials"). This replays the evaluation's adaptive loops
(``study_adaptive_predictor``'s replay: the same bases, committee, simulator seeds and budget) with a sample that
is one: every ``--every``-th step after the start design is a **probe**, a group drawn uniformly from the
unmeasured ones (seeded by the step), and the committee chooses the other steps **blind to the probes' data**
(from a second state that holds the start design and its own picks only), so that a probe's
leave-one-group-out error is distributed as an unmeasured group's. The reconstruction uses every group.

At every step it records the loop's own prediction (``predicted``) and three estimates of the unmeasured rows'
squared log-Y error from the probes' leave-one-group-out errors ``e`` (their sensor noise taken out as
:func:`~btfcore.acquisition.adaptive.fused_error` does; the fused measured rows' predicted error added, as the
predictor adds it):

- ``mean``: ``n_U`` times the probes' mean;
- ``ratio``: ``sum_U d * sum_P e / sum_P d``, ``d`` a group's disagreement of the blind committee (the committee
  gain, :meth:`~btfcore.acquisition.adaptive.AdaptiveState.committee_gains`), known for every unmeasured group;
- ``greg``: the generalised regression estimator ``n_U (mean_P e + b (mean_U d - mean_P d))``, ``b`` the probes'
  least-squares slope of ``e`` on ``d``.

It prints the issue's bar 1 (the probes cost shots) and bar 2 at the budget's stop and the target stops
(``tasks.adaptive.adaptive_bars``) with each estimate as the prediction from the ``--min-probes``-th probe on
(the loop's own before). About 45 s per material at the default scale on one core, 2 minutes at four turntable
positions (docs/adaptive-capture.md, "Samples of the unmeasured rows").

    .venv/bin/python benchmarks/study_adaptive_probes.py --db acq-db-s1 --eval out-s1 --seed 1 [--every 3]
"""

from __future__ import annotations

import contextlib
import copy
import json
from typing import Any, Iterator

import numpy as np

from btfcore.acquisition import adaptive as AD
from btfcore.acquisition.adaptive import FUSE_S2_FLOOR, LOG_YUV_EPS, REC709_LUMA, fused_error, luminance_noise
from study_adaptive_predictor import replay_held_out, replay_materials, replay_parser
from tasks import adaptive as TA

ESTIMATES = ("mean", "ratio", "greg")
_COMMITTEE_GAINS = AD.AdaptiveState.committee_gains                    # the loop's own, before :func:`probing`


@contextlib.contextmanager
def probing(every: int, seed: int) -> Iterator[None]:
    """``AdaptiveState`` with probe steps and a committee blind to the probes' data, while the context lasts."""
    init, add, gains = AD.AdaptiveState.__init__, AD.AdaptiveState.add, AD.AdaptiveState.committee_gains

    def init_(self, *args, blind: bool = False, **kwargs):
        init(self, *args, **kwargs)
        self.probes: list[int] = []
        self.blind = None if blind else AD.AdaptiveState(*args, blind=True, **kwargs)

    def add_(self, group, measured, gain):
        add(self, group, measured, gain)
        if self.blind is not None and group not in self.probes:
            self.blind.add(group, measured, gain)

    def gains_(self, model=None):
        if (len(self.groups) - self.unbiased_groups) % every:          # the committee's step, blind to the probes
            g = gains(self.blind)
            g[self.groups] = -np.inf
            return g
        cand = np.setdiff1d(np.arange(self.n_groups), self.groups)
        self.probes.append(int(np.random.default_rng([seed, len(self.groups)]).choice(cand)))
        g = np.full(self.n_groups, -np.inf)
        g[self.probes[-1]] = 1.0
        return g

    AD.AdaptiveState.__init__, AD.AdaptiveState.add, AD.AdaptiveState.committee_gains = init_, add_, gains_
    try:
        yield
    finally:
        AD.AdaptiveState.__init__, AD.AdaptiveState.add, AD.AdaptiveState.committee_gains = init, add, gains


def probe_errors(state: AD.AdaptiveState, m: dict[str, Any]) -> np.ndarray:
    """Each probe's squared log-Y error predicted from the other groups (exact for the linear solve), summed
    over its rows of the texel means; lit entries less their sensor noise, shadows their distance to eps."""
    eps, cap, n_cam = LOG_YUV_EPS, np.log(1 / LOG_YUV_EPS) ** 2, state.geometry.n_cam
    ys = state.y @ REC709_LUMA
    v = luminance_noise(state.y, state.gain, state.noise)
    out = []
    for group in state.probes:
        i = state.groups.index(group)
        sl = slice(i * n_cam, (i + 1) * n_cam)
        pred = state.group_held_out(m, ys, i)
        y = ys[sl]
        lit = (y * state.gain[sl][:, None] > state.noise.read_noise_e) & (y > eps)
        log_pred = np.log(np.maximum(pred, eps))
        lit_error = np.minimum((log_pred - np.log(np.maximum(y, eps))) ** 2, cap) - v[sl] / np.maximum(y, eps) ** 2
        e = np.where(lit, lit_error, (log_pred - np.log(eps)) ** 2)
        out.append(max(float(e.mean(axis=1).sum()), 0.0))
    return np.asarray(out)


def _recording(log: list[dict[str, Any]], truth: dict[str, np.ndarray]):
    """``AdaptiveState.predict`` that appends each step's probe count and estimates to ``log`` (the truth is
    scored by the loop itself)."""
    predict = AD.AdaptiveState.predict

    def wrapped(self: AD.AdaptiveState, model: dict | None = None) -> dict[str, float]:
        m = model or self._model()
        out = predict(self, m)
        rec: dict[str, Any] = {"n_probes": len(self.probes)}
        if len(self.probes) >= 3:
            e = probe_errors(self, m)
            d = _COMMITTEE_GAINS(self.blind)                           # every group's blind disagreement
            unmeasured = np.isfinite(d)
            unmeasured[self.probes] = False
            d_p, d_u, n_u = d[self.probes], d[unmeasured], int(unmeasured.sum())
            slope = np.cov(d_p, e)[0, 1] / max(float(np.var(d_p, ddof=1)), 1e-300)
            sums = {"mean": n_u * e.mean(), "ratio": d_u.sum() * e.sum() / max(d_p.sum(), 1e-300),
                    "greg": max(n_u * (e.mean() + slope * (d_u.mean() - d_p.mean())), 0.0)}
            Yhat = m["Yhat"]
            measured = float(np.sum(fused_error(Yhat[self.rows], self.y @ REC709_LUMA, self.gain, self.noise,
                                                max(float(m["s2"]), FUSE_S2_FLOOR))))
            ss = float(np.sum(np.log(np.maximum(Yhat, LOG_YUV_EPS)) ** 2))
            rec.update({k: float(np.sqrt((measured + v * len(self.sub)) / ss)) for k, v in sums.items()})
        log.append(rec)
        return out
    return wrapped


def _as_prediction(records: dict[str, Any], name: str, min_probes: int) -> dict[str, Any]:
    """The records with estimate ``name`` as each step's prediction from ``min_probes`` probes on."""
    out = copy.deepcopy(records)
    for rec in out.values():
        for step in rec["steps"]:
            if step["n_probes"] >= min_probes and name in step:
                step["predicted"] = step[name]
    return out


def main() -> None:
    p = replay_parser(__doc__)
    p.add_argument("--every", type=int, default=3, help="a probe every this many steps after the start design")
    p.add_argument("--min-probes", type=int, default=5, help="probes before an estimate replaces the prediction")
    a = p.parse_args()
    config, materials, chosen = replay_materials(a)
    records = {}
    with probing(a.every, a.seed):
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
        b = TA.adaptive_bars(records if name == "predicted" else _as_prediction(records, name, a.min_probes))
        print(f"bar 2, {name}: within 25 % at the budget {b['share_within_25pct']['posterior']:.2f}, at the target "
              "stops " + ", ".join(f"{t['share_within_25pct']:.2f}" for t in b["at_target_stop"].values()))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(records, f)


if __name__ == "__main__":
    main()
