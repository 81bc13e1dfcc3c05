"""The acquisition strategies of the evaluation: one registry of names, measurements and solve operators.

Every strategy of the acquisition evaluation (``docs/evaluation.md``,
"Strategies") is one entry of :data:`REGISTRY`: its name, the space it
reconstructs in, the measurement it reads, and the builder of its sampling
and solve operators. The names (:func:`strategy_names`), the operators
(:func:`build_strategies`) and the report's rows all come from it.

* paper 1 (den Brok et al.): ABRDF and 3x3 ABTF reconstruction in log Y,
  U/Y, V/Y (§3.3-3.4, eq. 3) from the 7x7 parabolic map (Fig. 3b) or random
  swap (Alg. 1), and the projection of the truth (Table 2, "proj");
* VMV paper §4.1: plain demultiplexing, projection and thresholded
  de-noising on a truncated SVD of linear RGB;
* paper 4: sparse (pinv, Tikhonov with :math:`\\lambda\\Sigma^{-1}`),
  multiplexed and sparse + multiplexed reconstruction on the ALS basis
  (§4.3, eq. 10; the sample counts of §5.2);
* beyond the thesis (issue 20): ``n_leds // 4`` basis-aware binary patterns
  (:mod:`btfcore.acquisition.illumination_patterns`) and as many S-matrix rows
  chosen on the same objective, each reconstructed in one noise-whitened solve
  of paper 4 eq. 10.

Rows of a BTF are ``(turntable, camera, light)``, view-major with the light
fastest: ``n_lv = n_turn * n_cam * n_leds`` light/view pairs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from btfcore.acquisition.illumination_patterns import (PatternModel, design_patterns, expected_error,
                                                      pattern_operator, random_patterns, select_rows)
from btfcore.acquisition.noise import SensorNoise
from btfcore.acquisition.reconstruct import LAMBDA_ALS, SolveOperator, abtf_operator, solve_operator
from btfcore.acquisition.sampling import multiplexed_basis, parabolic_map_sampling, random_swap

__all__ = ["FLOOR_COMPUTED", "FLOOR_EXACT", "FLOOR_INPUT", "FLOOR_NOTES", "REGISTRY", "THESIS_N_S", "THESIS_PAIRS",
           "Geometry", "Strategy", "StrategyBases", "StrategySpec", "build_strategies", "floor_kinds", "scaled_pairs",
           "strategy_names"]

#: The thesis' sparse pair counts (paper 4 §5.2: n_s of 2,376 (light, turntable) pairs, all 11 cameras).
THESIS_N_S = (100, 200, 400)
#: (light, turntable) pairs of the thesis' dome (198 LEDs x 12 positions).
THESIS_PAIRS = 198 * 12


#: What a strategy's noise-free floor is (docs/evaluation.md, "Noise-free floors"): the same strategy (sampling,
#: basis, solver, regularisation, thresholded rows) on the noise-free counterpart of its measurement, computed
#: (``FLOOR_COMPUTED``); exact (``FLOOR_EXACT``: plain S-matrix demultiplexing of noise-free images returns the
#: truth, VMV §3.2); or its own result (``FLOOR_INPUT``: it reads the noise-free truth, paper 1 Table 2 "proj").
FLOOR_COMPUTED, FLOOR_EXACT, FLOOR_INPUT = "computed", "exact", "noise-free input"
#: The reports' sentence for each kind of floor.
FLOOR_NOTES = {
    FLOOR_COMPUTED: "the same sampling, basis, solver and regularisation on noise-free measurements",
    FLOOR_EXACT: "zero: noise-free multiplexed images demultiplex to the truth exactly (VMV §3.2)",
    FLOOR_INPUT: "its own error: it reads the noise-free truth (the projection bound, paper 1 Table 2)",
}


def scaled_pairs(n_s: int, n_pairs: int) -> int:
    """The thesis' ``n_s`` of 2,376 (light, turntable) pairs scaled to a device with ``n_pairs`` pairs."""
    return max(1, int(round(n_s * n_pairs / THESIS_PAIRS)))


@dataclass(frozen=True)
class Geometry:
    """The light/view layout a measurement needs: views (turntable x camera) x LEDs, texture size."""

    n_turn: int
    n_cam: int
    n_leds: int
    height: int
    width: int

    @property
    def n_views(self) -> int:
        return self.n_turn * self.n_cam

    @property
    def n_lv(self) -> int:
        return self.n_views * self.n_leds


@dataclass
class Strategy:
    """One way of measuring and reconstructing.

    ``space`` is ``'log'`` (log Y, U/Y, V/Y bases, one operator per channel
    in that order; the log Y one may be an ABTF operator) or ``'linear'``
    (one operator ``'rgb'`` on linear RGB). ``source`` is the measurement it
    reads: ``'single'`` (single-light rows), ``'truth'`` (the noise-free
    truth), ``'demux'`` (the demultiplexed multiplexed measurement),
    ``'mux'`` (the multiplexed rows themselves) or ``'patterns'`` (every view
    under the strategy's own ``patterns`` ``(m, n_leds)``, each image exposed
    with its own gain of ``gains`` ``(n_views * m,)``, set once the images'
    maxima are known). ``rows`` index that source (None: all). An empty
    ``operators`` means "no reconstruction" (the plain demultiplexed BTF). ``info`` is reported. ``floor`` is the kind of its
    noise-free floor (:data:`FLOOR_COMPUTED`, :data:`FLOOR_EXACT`, :data:`FLOOR_INPUT`).
    """

    name: str
    space: str
    source: str
    rows: np.ndarray | None
    operators: dict[str, SolveOperator]
    info: dict[str, Any] = field(default_factory=dict)
    floor: str = FLOOR_COMPUTED
    patterns: np.ndarray | None = None
    gains: np.ndarray | None = None


@dataclass(frozen=True)
class StrategyBases:
    """The bases the strategies reconstruct with (anything with ``U`` ``(n_lv, k)`` and ``sigma`` ``(k,)``).

    ``log_yuv`` maps the channel names to the ABRDF bases of log Y, U/Y and
    V/Y, in that order (log Y first); ``abtf_log_y`` is the 3x3 ABTF patch
    basis of log Y, ``als`` paper 4's relative-error ALS basis of linear RGB
    and ``linear`` the plain truncated SVD of linear RGB (VMV §4.1).
    """

    log_yuv: dict[str, Any]
    abtf_log_y: Any
    als: Any
    linear: Any


def row_groups(geometry: Geometry, per_view: int) -> np.ndarray:
    """Group id ``turntable * per_view + j`` of every row ``(turntable, camera, j)`` (all cameras together)."""
    t = np.repeat(np.arange(geometry.n_turn), geometry.n_cam * per_view)
    j = np.tile(np.arange(per_view), geometry.n_views)
    return t * per_view + j


def _rows_of_groups(units: np.ndarray, geometry: Geometry, per_view: int) -> np.ndarray:
    """Rows (view-major, ``j`` fastest) of the chosen groups ``turntable * per_view + j``, sorted."""
    t, j = np.divmod(np.asarray(units, dtype=np.int64), per_view)
    rows = ((t[:, None] * geometry.n_cam + np.arange(geometry.n_cam)[None]) * per_view + j[:, None]).ravel()
    return np.sort(rows)


class _Design:
    """The samplings one held-out material's strategies share, each computed once on first use."""

    def __init__(self, bases: StrategyBases, geometry: Geometry, light_dir: np.ndarray, view_dir: np.ndarray,
                 variance: np.ndarray, patterns: np.ndarray, seed: int, abrdf_k_fraction: float,
                 sampling_steps: int, noise: SensorNoise | None = None, single_exposure: bool = False) -> None:
        self.bases, self.geometry, self.variance, self.patterns = bases, geometry, variance, patterns
        self.noise, self.single_exposure = noise or SensorNoise(), single_exposure
        self.light_dir, self.view_dir = light_dir, view_dir
        self.seed, self.abrdf_k_fraction, self.sampling_steps = seed, abrdf_k_fraction, sampling_steps
        self.U = {c: b.U for c, b in bases.log_yuv.items()}
        self.log_y = next(iter(self.U))
        self._abrdf_ops: dict[str, dict[str, SolveOperator]] = {}
        self._sparse: dict[int, tuple[np.ndarray, Any]] = {}

    # ---- paper 1
    @cached_property
    def pmap(self) -> np.ndarray:
        return np.asarray(parabolic_map_sampling(self.light_dir, self.view_dir, 7), dtype=np.int64)

    @cached_property
    def k_abrdf(self) -> int:
        return int(min(self.U[self.log_y].shape[1], max(1, int(self.abrdf_k_fraction * len(self.pmap)))))

    @cached_property
    def optimized(self) -> Any:
        return random_swap(self.U[self.log_y][:, :self.k_abrdf], len(self.pmap), max_steps=self.sampling_steps,
                           seed=self.seed)

    def rows(self, label: str) -> np.ndarray:
        return self.pmap if label == "pmap7" else np.asarray(self.optimized.rows, dtype=np.int64)

    def abrdf_ops(self, label: str) -> dict[str, SolveOperator]:
        """Pinv operators (paper 1 eq. 3) of every channel on the rows of sampling ``label``."""
        if label not in self._abrdf_ops:
            rows, k = self.rows(label), self.k_abrdf
            self._abrdf_ops[label] = {c: solve_operator(u[:, :min(k, u.shape[1], len(rows))], method="pinv",
                                                        rows=rows, fused=False, warn=c != self.log_y)
                                      for c, u in self.U.items()}   # log Y's condition is reported: no warning
        return self._abrdf_ops[label]

    @cached_property
    def projection_ops(self) -> dict[str, SolveOperator]:
        return {c: solve_operator(u[:, :self.k_abrdf], method="projection", fused=False) for c, u in self.U.items()}

    # ---- paper 4
    @cached_property
    def n_pairs(self) -> int:
        return self.geometry.n_turn * self.geometry.n_leds

    def sparse(self, n_thesis: int) -> tuple[np.ndarray, Any]:
        """Rows and random-swap result of the (turntable, LED) pairs for the thesis' ``n_thesis``."""
        if n_thesis not in self._sparse:
            g, als = self.geometry, self.bases.als
            n_s = scaled_pairs(n_thesis, self.n_pairs)
            # with fewer measured rows than vectors, kappa is taken on the leading vectors the rows can determine
            k_s = min(int(als.U.shape[1]), n_s * g.n_cam)
            US = als.U * als.sigma[None, :]
            sel = random_swap(US[:, :k_s], n_s, groups=row_groups(g, g.n_leds), max_steps=self.sampling_steps,
                              seed=self.seed + n_thesis)
            self._sparse[n_thesis] = (_rows_of_groups(np.asarray(sel.units), g, g.n_leds), sel)
        return self._sparse[n_thesis]

    @cached_property
    def sparse_multiplexed(self) -> tuple[np.ndarray, Any, int]:
        """Rows, random-swap result and n_s of the (turntable, pattern) pairs (paper 4 §4.3)."""
        g, als, n_p = self.geometry, self.bases.als, self.patterns.shape[0]
        n_s = scaled_pairs(THESIS_N_S[-1], g.n_turn * n_p)
        A = multiplexed_basis(self.patterns, als.U, als.sigma)
        sel = random_swap(A[:, :min(int(als.U.shape[1]), n_s * g.n_cam)], n_s, groups=row_groups(g, n_p),
                          max_steps=self.sampling_steps, seed=self.seed + 1)
        return _rows_of_groups(np.asarray(sel.units), g, n_p), sel, n_s

    # ---- issue 20: basis-aware illumination patterns
    @cached_property
    def pattern_model(self) -> PatternModel:
        als = self.bases.als
        return PatternModel(als.U, als.sigma, self.geometry.n_leds, self.noise, single_exposure=self.single_exposure)

    @cached_property
    def n_patterns(self) -> int:
        """Patterns of the designed and subsampled strategies: a quarter of the LEDs (the issue's m <= n/4)."""
        return max(1, self.geometry.n_leds // 4)

    @cached_property
    def designed(self) -> Any:
        """Refined by bit flips from the subsampled S-matrix rows (robust start)."""
        return design_patterns(self.pattern_model, self.n_patterns, seed=self.seed, sweeps=1,
                               start=self.subsampled.patterns)

    @cached_property
    def subsampled(self) -> Any:
        return select_rows(self.pattern_model, self.patterns, self.n_patterns)[1]

    def pattern_design(self, kind: str) -> Any:
        """The ``'designed'`` or ``'subsampled'`` :class:`~btfcore.acquisition.illumination_patterns.PatternDesign`."""
        return self.designed if kind == "designed" else self.subsampled

    def patterns_report(self) -> dict[str, Any]:
        """Predicted errors of the full S-matrix, the subsampled one, random and designed patterns, and the
        designed and subsampled patterns as lists of the LEDs on (for the time model)."""
        model, m = self.pattern_model, self.n_patterns
        out: dict[str, Any] = {"m": m, "n_leds": self.geometry.n_leds, "peak_factor": model.peak_factor,
                               "predicted_relative_error": {
                                   "full-s-matrix": expected_error(model, self.patterns).relative_error,
                                   "subsampled-s-matrix": self.subsampled.relative_error,
                                   "random": expected_error(model, random_patterns(model.n_leds, m, self.seed)
                                                            ).relative_error,
                                   "designed": self.designed.relative_error}}
        for name, design in (("designed", self.designed), ("subsampled", self.subsampled)):
            out[name] = {**design.summary(), "leds": [np.flatnonzero(p).tolist() for p in design.patterns]}
        return out

    def report(self) -> dict[str, Any]:
        """Sample counts, condition numbers and the selected pairs of the sparse strategies."""
        g = self.geometry
        out: dict[str, Any] = {"paper1": {"n_samples": len(self.pmap), "fraction": len(self.pmap) / g.n_lv,
                                          "k_abrdf": self.k_abrdf, "k_abtf": int(self.bases.abtf_log_y.U.shape[1]),
                                          "kappa_optimized": self.optimized.kappa}}
        counts = {}
        for n_thesis in THESIS_N_S:
            rows, sel = self.sparse(n_thesis)
            counts[str(n_thesis)] = {"n_s": scaled_pairs(n_thesis, self.n_pairs), "n_meas": int(len(rows)),
                                     "kappa": sel.kappa, "pairs": _pairs(sel, g.n_leds)}
        rows, sel, n_s = self.sparse_multiplexed
        out["paper4"] = {"k_als": int(self.bases.als.U.shape[1]), "n_pairs": self.n_pairs, "counts": counts,
                         "sparse_multiplexed": {"n_s": n_s, "n_meas": int(len(rows)), "kappa": sel.kappa,
                                                "pairs": _pairs(sel, self.patterns.shape[0])}}
        out["patterns"] = self.patterns_report()
        return out


def _pairs(sel: Any, per_turntable: int) -> list[list[int]]:
    return np.stack(np.divmod(np.asarray(sel.units, dtype=np.int64), per_turntable), axis=1).tolist()


#: What a builder returns: the rows of its source it reads (None: all), its operators and its report.
Built = tuple[np.ndarray | None, dict[str, SolveOperator], dict[str, Any]]


# --------------------------------------------------------------------------- builders, one per kind of strategy


def _abrdf(d: _Design, label: str) -> Built:
    rows, ops = d.rows(label), d.abrdf_ops(label)
    return rows, ops, {"paper": "1", "basis": "ABRDF (log Y, U/Y, V/Y)", "k": d.k_abrdf,
                       "n_meas": int(len(rows)), "kappa_log_y": ops[d.log_y].condition}


def _abtf(d: _Design, label: str) -> Built:
    rows = d.rows(label)
    abtf = abtf_operator(d.bases.abtf_log_y.U, rows, p=3, method="pinv", warn=False)   # kappa_log_y reported
    return rows, {**d.abrdf_ops(label), d.log_y: abtf}, {
        "paper": "1", "basis": "3x3 ABTF for log Y, ABRDF for U/Y and V/Y", "k": int(d.bases.abtf_log_y.U.shape[1]),
        "n_meas": int(len(rows)), "kappa_log_y": abtf.condition}


def _abrdf_projection(d: _Design, _: Any) -> Built:
    return None, dict(d.projection_ops), {"paper": "1", "basis": "ABRDF", "k": d.k_abrdf,
                                          "note": "truth projected (lower bound)"}


def _abtf_projection(d: _Design, _: Any) -> Built:
    all_rows = np.arange(d.geometry.n_lv)
    abtf = abtf_operator(d.bases.abtf_log_y.U, all_rows, p=3, method="pinv", warn=False)
    return all_rows, {**d.projection_ops, d.log_y: abtf}, {
        "paper": "1", "basis": "3x3 ABTF", "k": int(d.bases.abtf_log_y.U.shape[1]),
        "note": "truth projected (lower bound)"}


def _demultiplexed(d: _Design, _: Any) -> Built:
    return None, {}, {"paper": "VMV", "note": "no model"}


def _projection(d: _Design, _: Any) -> Built:
    U = d.bases.linear.U
    return None, {"rgb": solve_operator(U, method="projection", fused=False)}, {
        "paper": "VMV eq. den Brok", "basis": "class truncated SVD (linear RGB)", "k": int(U.shape[1])}


def _thresholded(d: _Design, _: Any) -> Built:
    # VMV §4.1: rows above the 9th decile of the variance of the linear ("unnormalised") demultiplexed
    # textures left out of the projection on the class's truncated SVD of linear RGB ("D ~ U Sigma V^T")
    U = d.bases.linear.U
    thr = solve_operator(U, method="thresholded", variance=d.variance, fused=False, warn=False)  # condition reported
    return None, {"rgb": thr}, {"paper": "VMV §4.1", "basis": "class truncated SVD (linear RGB)", "decile": 9,
                                "k": int(U.shape[1]), "variance": "linear demultiplexed RGB per texture",
                                "condition": thr.condition}


def _sparse_tikhonov(d: _Design, n_thesis: int) -> Built:
    rows, _ = d.sparse(n_thesis)
    als = d.bases.als
    tik = solve_operator(als.U, als.sigma, method="tikhonov", rows=rows, lam=LAMBDA_ALS, fused=False)
    return rows, {"rgb": tik}, {"paper": "4", "lam": LAMBDA_ALS, "n_s": scaled_pairs(n_thesis, d.n_pairs),
                                "k": int(als.U.shape[1]), "n_meas": int(len(rows)), "condition": tik.condition}


def _sparse_pinv(d: _Design, n_thesis: int) -> Built:
    rows, _ = d.sparse(n_thesis)
    k_p = min(int(d.bases.als.U.shape[1]), len(rows))
    pinv = solve_operator(d.bases.als.U[:, :k_p], method="pinv", rows=rows, fused=False, warn=False)  # reported
    return rows, {"rgb": pinv}, {"paper": "1 eq. 3", "n_s": scaled_pairs(n_thesis, d.n_pairs), "k": k_p,
                                 "n_meas": int(len(rows)), "condition": pinv.condition}


def _multiplexed(d: _Design, _: Any) -> Built:
    als = d.bases.als
    mux = solve_operator(als.U, als.sigma, method="direct", patterns=d.patterns, lam=LAMBDA_ALS, fused=False)
    return None, {"rgb": mux}, {"paper": "4 eq. 10", "lam": LAMBDA_ALS, "k": int(als.U.shape[1]),
                                "n_meas": int(d.geometry.n_views * d.patterns.shape[0]), "condition": mux.condition}


def _sparse_multiplexed(d: _Design, _: Any) -> Built:
    rows, _, n_s = d.sparse_multiplexed
    als = d.bases.als
    sm = solve_operator(als.U, als.sigma, method="direct", patterns=d.patterns, rows=rows, lam=LAMBDA_ALS,
                        fused=False)
    return rows, {"rgb": sm}, {"paper": "4 eq. 10", "lam": LAMBDA_ALS, "n_s": n_s, "k": int(als.U.shape[1]),
                               "n_meas": int(len(rows)), "condition": sm.condition}


def _illumination_patterns(d: _Design, kind: str) -> Built:
    design = d.pattern_design(kind)
    op = pattern_operator(d.pattern_model, design.patterns)
    return None, {"rgb": op}, {
        "paper": "issue 20: Ratner & Schechner 2007; paper 4 eq. 10, noise-whitened",
        "patterns": "basis-aware binary (S-matrix rows refined by bit flips)" if kind == "designed"
        else "S-matrix rows chosen on the same objective", "m": design.m, "k": int(d.bases.als.U.shape[1]),
        "n_meas": int(d.geometry.n_views * design.m), "condition": op.condition,
        "predicted_relative_error": design.relative_error, "leds_on_mean": float(design.leds_on.mean())}


# --------------------------------------------------------------------------- the registry


@dataclass(frozen=True)
class StrategySpec:
    """One entry of :data:`REGISTRY`: a strategy's name, space, source and builder (called with ``arg``), and
    the kind of its noise-free floor (:data:`FLOOR_COMPUTED` unless said otherwise)."""

    name: str
    space: str
    source: str
    build: Callable[[_Design, Any], Built]
    arg: Any = None
    floor: str = FLOOR_COMPUTED


#: Every strategy of the evaluation, in report order (docs/evaluation.md, "Strategies").
REGISTRY: tuple[StrategySpec, ...] = (
    *(StrategySpec(f"{model}-{label}", "log", "single", build, label)
      for label in ("pmap7", "optimized") for model, build in (("abrdf", _abrdf), ("abtf", _abtf))),
    StrategySpec("abrdf-projection", "log", "truth", _abrdf_projection, floor=FLOOR_INPUT),
    StrategySpec("abtf-projection", "log", "truth", _abtf_projection, floor=FLOOR_INPUT),
    StrategySpec("demultiplexed", "log", "demux", _demultiplexed, floor=FLOOR_EXACT),
    StrategySpec("projection", "linear", "demux", _projection),
    StrategySpec("thresholded", "linear", "demux", _thresholded),
    *(StrategySpec(f"sparse-{kind}-n{n}", "linear", "single", build, n)
      for n in THESIS_N_S for kind, build in (("tikhonov", _sparse_tikhonov), ("pinv", _sparse_pinv))),
    StrategySpec("multiplexed-direct", "linear", "mux", _multiplexed),
    StrategySpec(f"sparse-multiplexed-n{THESIS_N_S[-1]}", "linear", "mux", _sparse_multiplexed),
    StrategySpec("patterns-quarter", "linear", "patterns", _illumination_patterns, "designed"),
    StrategySpec("smatrix-quarter", "linear", "patterns", _illumination_patterns, "subsampled"),
)


def strategy_names() -> list[str]:
    """Names of the strategies :func:`build_strategies` makes, in its order (those of :data:`REGISTRY`)."""
    return [spec.name for spec in REGISTRY]


def floor_kinds() -> dict[str, str]:
    """``{strategy: kind of its noise-free floor}`` of every strategy of :data:`REGISTRY`, in its order."""
    return {spec.name: spec.floor for spec in REGISTRY}


def build_strategies(bases: StrategyBases, geometry: Geometry, light_dir: np.ndarray, view_dir: np.ndarray,
                     variance: np.ndarray, patterns: np.ndarray, seed: int, *, abrdf_k_fraction: float = 0.75,
                     sampling_steps: int = 1500, noise: SensorNoise | None = None, single_exposure: bool = False
                     ) -> tuple[list[Strategy], dict[str, Any]]:
    """Samplings and solve operators of every strategy of :data:`REGISTRY` for one held-out material.

    Parameters
    ----------
    bases : StrategyBases
        The held-out material's class bases (leave-one-out).
    geometry : Geometry
        Layout of the ``n_lv`` rows.
    light_dir, view_dir : (n_lv, 3) ndarray
        Directions of every row (the parabolic map, paper 1 Fig. 3b).
    variance : (n_lv,) ndarray
        Per-texture variance of the linear demultiplexed RGB, over texels and
        channels (the thresholded de-noising, VMV §4.1: "unnormalised" data).
    patterns : (n_p, n_leds) ndarray
        S-matrix patterns of every view.
    seed : int
        Seed of the random-swap samplers (paper 1 Alg. 1).
    abrdf_k_fraction : float
        ABRDF bases use at most this fraction of the parabolic-map sample count as vectors.
    sampling_steps : int
        Steps of every random-swap sampler.
    noise : SensorNoise, optional
        The sensor the basis-aware patterns are designed for (default :class:`SensorNoise` ()).
    single_exposure : bool
        The dome exposes every pattern of a view with one gain metered on the view's median pattern
        (:class:`~btfcore.acquisition.illumination_patterns.PatternModel`); the patterns are designed for it.

    Returns
    -------
    strategies, sampling : list of Strategy, dict
        ``sampling`` reports the sample counts, condition numbers and the
        selected (turntable, LED / pattern) pairs of the sparse strategies.
    """
    design = _Design(bases, geometry, light_dir, view_dir, variance, patterns, seed, abrdf_k_fraction,
                     sampling_steps, noise, single_exposure)
    strategies = [Strategy(spec.name, spec.space, spec.source, *spec.build(design, spec.arg), floor=spec.floor,
                           patterns=design.pattern_design(spec.arg).patterns if spec.source == "patterns" else None)
                  for spec in REGISTRY]
    return strategies, design.report()
