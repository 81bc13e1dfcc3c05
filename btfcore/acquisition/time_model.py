"""Acquisition-time model of a camera dome, fitted to the thesis' published times.

The model predicts how long a device takes to execute a
:class:`~btfcore.acquisition.plan.CapturePlan`, with a breakdown into shutter time,
per-exposure and per-shot overheads, LED switching and turntable moves. Its
two overhead parameters are fitted by least squares on (at most) two published
acquisition times of the thesis' DOME II and then predict the others
(:func:`fit_time_model`, :data:`PUBLISHED_FIGURES`).

Model
-----
For a plan of shots :math:`s` with exposure brackets :math:`t_{s,1..K_s}`
(seconds), :math:`|C_s|` cameras, :math:`P` cameras that can fire in
parallel, frame rate :math:`f`,

.. math::
    T = T_{setup} + n_{moves} \\, T_{turn}
        + \\sum_s \\Big( \\lceil |C_s| / P \\rceil
          \\sum_{k=1}^{K_s} \\max\\big(t_{s,k} + c_{exp},\\; 1/f\\big)
          + c_{shot} + c_{led} [\\text{pattern}_s \\ne \\text{pattern}_{s-1}] \\Big)

with :math:`c_{exp}` the per-exposure overhead (read-out and transfer of one
frame from every camera: it is paid once per exposure step because the
cameras of a dome expose and transfer in parallel), :math:`c_{shot}` the
per-shot overhead (switching to the pattern, starting the bracket, writing the
files) and :math:`n_{moves}` the number of turntable positions visited (a
move precedes each run of consecutive shots at one position; DOME II is
"rotated 12 times by 30°"). No exposure step is faster than the cameras'
frame period :math:`1/f`.

The published times used are those of the thesis (see
:data:`VMV_TABLE2`, :data:`PUBLISHED_FIGURES`).

References
----------
.. [1] The thesis, App. VMV paper ("Fast multiplexed acquisition of
   high-dynamic-range material appearance"): §5.1 (11 cameras, maximum frame
   rate 8 Hz, 198 LEDs; 12 turntable positions of 30°), Table 2 (shutter times
   [ms] and acquisition times [h], single light vs multiplexed), §5.2 with
   Table 2 (4 exposure steps single-light, 1-2 multiplexed), §5.3
   (bootstrapping "approximately 9 hours, as opposed to almost 24 hours").
   Paper 4 "Rapid material capture through sparse and multiplexed
   measurements": §5.2 (n_s pairs of light source and turntable rotation,
   all cameras), §5.4 ("between 1.2 and 4 h ... 12-22 min").
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Sequence

import numpy as np

from btfcore.acquisition.plan import (
    CapturePlan,
    ExposureModel,
    bootstrapping_plan,
    full_single_light_plan,
    multiplexed_plan,
    sparse_multiplexed_plan,
    sparse_plan,
)
from btfcore.dome import Device, get_device

__all__ = [
    "DEFAULT_FIT_ON",
    "DEFAULT_FREE",
    "PUBLISHED_FIGURES",
    "VMV_TABLE2",
    "PredictionRow",
    "PublishedFigure",
    "TimeBreakdown",
    "TimeModelFit",
    "TimeModelParams",
    "describe",
    "fit_time_model",
    "predict_time",
    "published_plan",
    "thesis_exposure",
]


# --------------------------------------------------------------------------- published data

#: VMV paper ("Fast multiplexed acquisition ..."), Table 2: shutter
#: times [ms] and acquisition times [h], single light vs multiplexed (S-matrix
#: order 199), DOME II, 4 material patches measured at once. Single-light
#: brackets were taken at 10 dB camera gain, multiplexed at 0 dB (VMV paper §5.1).
VMV_TABLE2: dict[str, dict[str, Any]] = {
    "cloth": {"single_ms": (150.0, 608.2, 2466.2, 10000.0), "multiplexed_ms": (15.0, 45.0),
              "single_h": 10.8, "multiplexed_h": 1.8, "rel_delta": -0.83},
    "leather": {"single_ms": (10.0, 144.2, 2080.1, 30000.0), "multiplexed_ms": (30.0,),
                "single_h": 23.6, "multiplexed_h": 1.2, "rel_delta": -0.95},
    "wood": {"single_ms": (10.0, 60.4, 364.4, 2200.0), "multiplexed_ms": (20.0,),
             "single_h": 4.4, "multiplexed_h": 1.2, "rel_delta": -0.75},
}

#: Sparse samples of paper 4's combined experiments (paper 4 §5.4).
PAPER4_N_SPARSE = 400


@dataclass(frozen=True)
class PublishedFigure:
    """One acquisition time published in the thesis.

    Parameters
    ----------
    key : str
        Short id, e.g. ``"leather-multiplexed"``.
    material : {'cloth', 'leather', 'wood'}
        Whose VMV Table 2 shutter times the plan uses.
    strategy : str
        ``"single"``, ``"multiplexed"``, ``"sparse-single"``,
        ``"sparse-multiplexed"`` or ``"bootstrapping"``.
    hours : float
        The published acquisition time.
    source : str
        Where in the thesis.
    note : str
        How the figure was read (an endpoint of a range, an approximation).
    bar : bool
        Whether it is one of the figures the model must meet within 25 %.
    """

    key: str
    material: str
    strategy: str
    hours: float
    source: str
    note: str = ""
    bar: bool = True


#: The published acquisition times the model is fitted to and judged on.
PUBLISHED_FIGURES: tuple[PublishedFigure, ...] = (
    *(PublishedFigure(f"{m}-{kind}", m, kind, VMV_TABLE2[m][f"{kind}_h"], "VMV Table 2",
                      "full acquisition, 12 turntable positions x "
                      + ("198 single LEDs, 4 exposure steps" if kind == "single"
                         else f"199 S-matrix patterns, {len(VMV_TABLE2[m]['multiplexed_ms'])} exposure step(s)"))
      for m in ("cloth", "leather", "wood") for kind in ("single", "multiplexed")),
    PublishedFigure("p4-sparse-multiplexed-min", "leather", "sparse-multiplexed", 12 / 60,
                    "paper 4 §5.4",
                    "lower end of '12-22 min', n_s = 400 (pattern, turntable) pairs; read as the leather (the "
                    "faster multiplexed material); paper 4's samples are not the VMV ones, VMV shutter times assumed"),
    PublishedFigure("p4-sparse-multiplexed-max", "cloth", "sparse-multiplexed", 22 / 60,
                    "paper 4 §5.4",
                    "upper end of '12-22 min', n_s = 400; read as the cloth; VMV shutter times assumed"),
    PublishedFigure("p4-sparse-single-max", "leather", "sparse-single", 4.0,
                    "paper 4 §5.2, §5.4",
                    "upper end of 'between 1.2 and 4 h' (the lower end is the full multiplexed leather, "
                    "1.2 h, above): sparse single-light, n_s = 400 (LED, turntable) pairs, leather"),
    PublishedFigure("leather-bootstrapping", "leather", "bootstrapping", 9.0, "VMV §5.3",
                    "'approximately 9 hours'; quadrant brackets not published: single-light bracket / m "
                    "(ExposureModel, exponent 1) for the order-47 patterns", bar=False),
)

#: The two figures the overhead parameters are fitted on by default: in the
#: multiplexed acquisitions the shutter adds up to < 3 % of the time, so they
#: measure the overheads almost directly and differ in the exposure steps
#: (1 vs 2), which separates c_exp from c_shot.
DEFAULT_FIT_ON: tuple[str, ...] = ("leather-multiplexed", "cloth-multiplexed")
#: Parameters fitted by default.
DEFAULT_FREE: tuple[str, ...] = ("exposure_overhead_s", "shot_overhead_s")


def thesis_exposure(material: str) -> ExposureModel:
    """Exposure model with VMV Table 2's brackets for one material.

    Parameters
    ----------
    material : {'cloth', 'leather', 'wood'}

    Returns
    -------
    exposure : ExposureModel
        The single-light bracket, and the measured multiplexed bracket for
        patterns of 99 and 100 LEDs (the rows of the order-199 S-matrix
        truncated to 198 LEDs); other pattern sizes scale by ``1/m``.
    """
    if material not in VMV_TABLE2:
        raise ValueError(f"material {material!r} is not in VMV Table 2; choose one of {', '.join(VMV_TABLE2)}")
    row = VMV_TABLE2[material]
    return ExposureModel(single_ms=row["single_ms"],
                         measured_ms={99: row["multiplexed_ms"], 100: row["multiplexed_ms"]})


# --------------------------------------------------------------------------- model


@dataclass(frozen=True)
class TimeModelParams:
    """Parameters of the acquisition-time model (see the module notes).

    Parameters
    ----------
    exposure_overhead_s : float
        :math:`c_{exp}`, per exposure step: read-out and transfer. The default
        is :func:`fit_time_model` on :data:`DEFAULT_FIT_ON`, rounded.
    shot_overhead_s : float
        :math:`c_{shot}`, per shot: pattern set-up, bracket start, storage
        (default: fitted likewise).
    frame_rate_hz : float
        :math:`f`, the cameras' maximum frame rate (DOME II: 8 Hz).
    parallel_cameras : int or None
        :math:`P`, cameras that expose at once; None: all of a shot's cameras.
    led_switch_s : float
        :math:`c_{led}`, per change of LED pattern (0: folded into
        ``shot_overhead_s``, which it cannot be told apart from on the
        published figures).
    turntable_move_s : float
        :math:`T_{turn}`, per turntable move incl. settling. Not published and
        not identifiable from full acquisitions (always 12 moves); assumed.
    setup_s : float
        :math:`T_{setup}`, fixed per acquisition (0: not identifiable either).
    """

    exposure_overhead_s: float = 0.875
    shot_overhead_s: float = 0.879
    frame_rate_hz: float = 8.0
    parallel_cameras: int | None = None
    led_switch_s: float = 0.0
    turntable_move_s: float = 5.0
    setup_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("exposure_overhead_s", "shot_overhead_s", "led_switch_s", "turntable_move_s", "setup_s"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"TimeModelParams.{name} must be finite and >= 0 s, got {v}")
            object.__setattr__(self, name, v)
        if not (math.isfinite(self.frame_rate_hz) and self.frame_rate_hz > 0):
            raise ValueError(f"TimeModelParams.frame_rate_hz must be finite and > 0, got {self.frame_rate_hz}")
        if self.parallel_cameras is not None and int(self.parallel_cameras) < 1:
            raise ValueError(f"TimeModelParams.parallel_cameras must be >= 1 or None, got {self.parallel_cameras}")

    def replace(self, **changes: Any) -> "TimeModelParams":
        """A copy with some fields changed (validated)."""
        return replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form."""
        return asdict(self)


@dataclass(frozen=True)
class TimeBreakdown:
    """Predicted acquisition time of a plan, seconds, by cause.

    Parameters
    ----------
    shutter_s : float
        Sum of the shutter times (times camera groups).
    exposure_overhead_s : float
        Per-exposure overhead, incl. waiting for the frame period.
    shot_overhead_s : float
    led_switch_s : float
    turntable_s : float
    setup_s : float
    n_shots, n_exposures, n_turntable_moves, n_pattern_changes : int
    """

    shutter_s: float
    exposure_overhead_s: float
    shot_overhead_s: float
    led_switch_s: float
    turntable_s: float
    setup_s: float
    n_shots: int
    n_exposures: int
    n_turntable_moves: int
    n_pattern_changes: int

    @property
    def total_s(self) -> float:
        """Predicted acquisition time, seconds."""
        return (self.shutter_s + self.exposure_overhead_s + self.shot_overhead_s + self.led_switch_s
                + self.turntable_s + self.setup_s)

    @property
    def total_h(self) -> float:
        """Predicted acquisition time, hours."""
        return self.total_s / 3600.0

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form with ``total_s`` and ``total_h``."""
        d = asdict(self)
        d["total_s"] = self.total_s
        d["total_h"] = self.total_h
        return d


@dataclass(frozen=True)
class _PlanArrays:
    exp_shot: np.ndarray      # (n_exp,) shot index of each exposure step
    exp_t_s: np.ndarray       # (n_exp,) shutter time, s
    shot_n_cam: np.ndarray    # (n_shots,) cameras per shot
    n_moves: int
    n_changes: int


def _arrays(plan: CapturePlan) -> _PlanArrays:
    shots = plan.shots
    exp_shot = np.repeat(np.arange(len(shots)), [s.n_exposures for s in shots])
    exp_t = np.array([t for s in shots for t in s.shutter_ms], dtype=np.float64) / 1000.0
    n_cam = np.array([len(s.cameras) for s in shots], dtype=np.int64)
    moves = sum(1 for i, s in enumerate(shots) if i == 0 or s.turntable != shots[i - 1].turntable)
    changes = sum(1 for i, s in enumerate(shots) if i == 0 or s.leds != shots[i - 1].leds)
    return _PlanArrays(exp_shot, exp_t, n_cam, moves, changes)


def _breakdown(a: _PlanArrays, p: TimeModelParams) -> TimeBreakdown:
    n_shots = len(a.shot_n_cam)
    par = p.parallel_cameras
    groups = np.ones(n_shots) if par is None else np.ceil(a.shot_n_cam / int(par))      # ceil(|C_s| / P)
    g = groups[a.exp_shot] if n_shots else np.zeros(0)
    step = np.maximum(a.exp_t_s + p.exposure_overhead_s, 1.0 / p.frame_rate_hz)         # max(t + c_exp, 1/f)
    shutter = float(np.sum(g * a.exp_t_s))
    return TimeBreakdown(
        shutter_s=shutter,
        exposure_overhead_s=float(np.sum(g * step)) - shutter,
        shot_overhead_s=n_shots * p.shot_overhead_s,
        led_switch_s=a.n_changes * p.led_switch_s,
        turntable_s=a.n_moves * p.turntable_move_s,
        setup_s=p.setup_s if n_shots else 0.0,
        n_shots=n_shots, n_exposures=int(len(a.exp_t_s)), n_turntable_moves=a.n_moves,
        n_pattern_changes=a.n_changes,
    )


def predict_time(plan: CapturePlan, params: TimeModelParams | None = None) -> TimeBreakdown:
    """Predicted acquisition time of a plan.

    Parameters
    ----------
    plan : CapturePlan
    params : TimeModelParams, optional
        Default :class:`TimeModelParams` () (DOME II, overheads fitted on
        :data:`DEFAULT_FIT_ON`).

    Returns
    -------
    breakdown : TimeBreakdown
        ``breakdown.total_h`` is the predicted time in hours.

    Notes
    -----
    See the module docstring for the equation.
    """
    return _breakdown(_arrays(plan), params or TimeModelParams())


# --------------------------------------------------------------------------- published plans


def _sparse_selection(n_turn: int, n_cols: int, n: int, seed: int = 0) -> np.ndarray:
    """``n`` distinct (turntable, column) pairs, seeded; spread over the turntable positions."""
    flat = np.sort(np.random.default_rng(seed).choice(n_turn * n_cols, size=n, replace=False))
    return np.stack(np.divmod(flat, n_cols), axis=1)


def published_plan(figure: PublishedFigure | str, device: Device | None = None) -> CapturePlan:
    """The plan of a published acquisition, on the thesis' device.

    Parameters
    ----------
    figure : PublishedFigure or str
        One of :data:`PUBLISHED_FIGURES` or its key.
    device : Device, optional
        Default ``get_device("bonn-dome2")`` (11 cameras, 198 LEDs, 12
        turntable positions).

    Returns
    -------
    plan : CapturePlan
        With VMV Table 2's brackets for the figure's material. Sparse plans
        draw :data:`PAPER4_N_SPARSE` pairs with a fixed seed (the time depends
        only on their number and on the turntable positions visited).
        Bootstrapping uses sector 0 of half-width 50°, which leaves at most 47
        LEDs in each other quadrant -- the thesis' order 47 (VMV §5.1).
    """
    fig = _figure(figure)
    device = device or get_device("bonn-dome2")
    exposure = thesis_exposure(fig.material)
    if fig.strategy == "single":
        return full_single_light_plan(device, exposure)
    if fig.strategy == "multiplexed":
        return multiplexed_plan(device, exposure)
    if fig.strategy == "sparse-single":
        return sparse_plan(device, _sparse_selection(device.n_turn, device.n_leds, PAPER4_N_SPARSE), exposure)
    if fig.strategy == "sparse-multiplexed":
        n_pat = multiplexed_plan(device, exposure, turntables=[0]).n_shots
        return sparse_multiplexed_plan(device, _sparse_selection(device.n_turn, n_pat, PAPER4_N_SPARSE),
                                       exposure, select="patterns")
    if fig.strategy == "bootstrapping":
        return bootstrapping_plan(device, exposure, specular_half_width_deg=50.0)
    raise ValueError(f"figure {fig.key!r} has unknown strategy {fig.strategy!r}")


def _figure(figure: PublishedFigure | str) -> PublishedFigure:
    if isinstance(figure, PublishedFigure):
        return figure
    for f in PUBLISHED_FIGURES:
        if f.key == figure:
            return f
    raise ValueError(f"unknown published figure {figure!r}; choose one of "
                     f"{', '.join(f.key for f in PUBLISHED_FIGURES)}")


# --------------------------------------------------------------------------- fit


@dataclass(frozen=True)
class PredictionRow:
    """Published vs predicted acquisition time of one figure."""

    key: str
    material: str
    strategy: str
    published_h: float
    predicted_h: float
    fitted: bool
    bar: bool
    source: str
    note: str
    breakdown: TimeBreakdown

    @property
    def rel_error(self) -> float:
        """``predicted / published - 1``."""
        return self.predicted_h / self.published_h - 1.0

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form."""
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "breakdown"}
        d["rel_error"] = self.rel_error
        d["breakdown"] = self.breakdown.to_dict()
        return d


@dataclass(frozen=True)
class TimeModelFit:
    """Fitted time-model parameters and the table of predicted vs published times."""

    params: TimeModelParams
    fit_on: tuple[str, ...]
    free: tuple[str, ...]
    rows: tuple[PredictionRow, ...]

    def row(self, key: str) -> PredictionRow:
        """The row of one figure."""
        for r in self.rows:
            if r.key == key:
                return r
        raise ValueError(f"no row {key!r}; rows: {', '.join(r.key for r in self.rows)}")

    def max_abs_rel_error(self, *, bar_only: bool = True, predicted_only: bool = True) -> float:
        """Largest ``|rel_error|`` over the predicted (not fitted) bar figures."""
        errs = [abs(r.rel_error) for r in self.rows
                if (r.bar or not bar_only) and (not r.fitted or not predicted_only)]
        return max(errs) if errs else 0.0

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form."""
        return {"params": self.params.to_dict(), "fit_on": list(self.fit_on), "free": list(self.free),
                "rows": [r.to_dict() for r in self.rows]}

    def table_markdown(self) -> str:
        """The prediction table as Markdown (for reports)."""
        lines = ["| figure | published | predicted | rel. error | role |", "|---|---:|---:|---:|---|"]
        for r in self.rows:
            fmt = (lambda h: f"{h * 60:.1f} min") if r.published_h < 1 else (lambda h: f"{h:.2f} h")
            role = "fitted" if r.fitted else ("predicted" if r.bar else "predicted (outside the bar)")
            lines.append(f"| {r.key} | {fmt(r.published_h)} | {fmt(r.predicted_h)} | "
                         f"{100 * r.rel_error:+.1f} % | {role} |")
        return "\n".join(lines)


def fit_time_model(fit_on: Sequence[str] = DEFAULT_FIT_ON, *, device: Device | None = None,
                   base: TimeModelParams | None = None, free: Sequence[str] = DEFAULT_FREE,
                   figures: Sequence[PublishedFigure] = PUBLISHED_FIGURES) -> TimeModelFit:
    """Fit the overhead parameters on published times and predict the others.

    Parameters
    ----------
    fit_on : sequence of str
        Keys of :data:`PUBLISHED_FIGURES` to fit on (at least ``len(free)``).
    device : Device, optional
        Default ``get_device("bonn-dome2")``.
    base : TimeModelParams, optional
        Values of the parameters that are not fitted (frame rate 8 Hz,
        turntable move 5 s, ...).
    free : sequence of str
        Names of :class:`TimeModelParams` fields to fit (non-negative).
    figures : sequence of PublishedFigure
        Figures to tabulate.

    Returns
    -------
    fit : TimeModelFit
        Fitted parameters and one :class:`PredictionRow` per figure.

    Notes
    -----
    Minimises the relative residuals
    :math:`\\sum_{i \\in fit} (T_i(\\theta) / T_i^{pub} - 1)^2` over
    :math:`\\theta \\ge 0` (``scipy.optimize.least_squares``); with two
    figures and two free parameters it solves them exactly when a
    non-negative solution exists.
    """
    from scipy.optimize import least_squares

    base = base or TimeModelParams()
    names = {f.name for f in fields(TimeModelParams)} - {"parallel_cameras"}
    bad = [n for n in free if n not in names]
    if bad or not free:
        raise ValueError(f"free parameters {bad or '[]'} are not fittable; choose from {', '.join(sorted(names))}")
    figs = {f.key: f for f in figures}
    missing = [k for k in fit_on if k not in figs]
    if missing:
        raise ValueError(f"fit_on figures {missing} are unknown; choose from {', '.join(figs)}")
    if len(fit_on) < len(free):
        raise ValueError(f"fitting {len(free)} parameters needs at least as many figures, got {len(fit_on)}")
    device = device or get_device("bonn-dome2")
    arrays = {k: _arrays(published_plan(f, device)) for k, f in figs.items()}
    target = np.array([figs[k].hours * 3600.0 for k in fit_on])

    def params_of(theta: np.ndarray) -> TimeModelParams:
        return base.replace(**{n: float(v) for n, v in zip(free, theta)})

    def residual(theta: np.ndarray) -> np.ndarray:
        p = params_of(theta)
        return np.array([_breakdown(arrays[k], p).total_s for k in fit_on]) / target - 1.0

    x0 = np.array([max(getattr(base, n), 0.1) for n in free])
    sol = least_squares(residual, x0, bounds=(0.0, np.inf), x_scale=1.0, xtol=1e-12, ftol=1e-12, gtol=1e-12)
    params = params_of(sol.x)
    rows = []
    for k, f in figs.items():
        b = _breakdown(arrays[k], params)
        rows.append(PredictionRow(f.key, f.material, f.strategy, f.hours, b.total_h, k in fit_on, f.bar,
                                  f.source, f.note, b))
    return TimeModelFit(params, tuple(fit_on), tuple(free), tuple(rows))


def describe(fit: TimeModelFit) -> str:
    """Fitted parameters and prediction table as Markdown."""
    p = fit.params
    head = (f"Fitted on {', '.join(fit.fit_on)}: c_exp = {p.exposure_overhead_s:.3f} s, "
            f"c_shot = {p.shot_overhead_s:.3f} s (fixed: f = {p.frame_rate_hz:g} Hz, "
            f"T_turn = {p.turntable_move_s:g} s, c_led = {p.led_switch_s:g} s, T_setup = {p.setup_s:g} s)")
    return head + "\n\n" + fit.table_markdown()

