"""Acquisition plans: which turntable position, LED pattern, cameras and shutter times, shot by shot.

A :class:`CapturePlan` is the ordered list of :class:`Shot` s an acquisition
device executes. One shot is one illumination pattern at one turntable
position, captured by a set of cameras (in a dome all cameras fire at once)
with an exposure bracket of one or more shutter times. The plan is pure data:
it names LEDs, cameras and turntable positions by their index in a
:class:`~btfcore.dome.Device`, and :func:`validate_plan` checks
that the device has them.

Strategies (functions returning a plan for a device)
----------------------------------------------------
* :func:`full_single_light_plan` -- every LED alone at every turntable position
  (the brute-force reference measurement; thesis §1.1.3, VMV paper §5.1).
* :func:`sparse_plan` -- only selected (turntable, LED) pairs, all cameras
  (paper 4, §5: "only choose from pairs of light sources and turntable
  rotations and then always use all cameras available").
* :func:`multiplexed_plan` -- the S-matrix patterns of the device's LEDs at
  every turntable position (VMV paper §3.2, §5.1: order 199 for 198 LEDs).
* :func:`sparse_multiplexed_plan` -- selected (turntable, S-matrix row) pairs
  (paper 4, eq. 4: :math:`\\mathbf{S}\\mathbf{M}\\mathbf{B}`), or S-matrices
  over the LEDs selected at each turntable position.
* :func:`bootstrapping_plan` -- VMV paper §4.2: the LED hemisphere in
  quadrants, the quadrant opposite the cameras (mirror directions, Fresnel
  effect) single-light, the other quadrants each with its own smaller S-matrix.

Exposure
--------
Shutter times come from an :class:`ExposureModel`: a single-light bracket and
a rule for a pattern with ``m`` LEDs on (by default the bracket scaled by
``1 / m``; measured brackets can be given per ``m``).

The plan's JSON/CSV form is written by :mod:`tasks.plan`; the predicted
acquisition time comes from :mod:`btfcore.acquisition.time_model`, and
:func:`multiplexing_gain` predicts whether the plan's multiplexed shots beat
single-light capture under the sensor's photon + read noise.

References
----------
.. [1] The thesis, VMV paper ("Fast multiplexed acquisition of high-dynamic-range
   material appearance") §4.2 (database bootstrapping), §5.1 (device and
   orders), Table 2; paper 4 ("Rapid material capture through sparse and
   multiplexed measurements") §5.2 (camera-parallel sampling) and §5.4
   (sparse multiplexed acquisition, n_s = 400, acquisition times).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.capture.demultiplex import demultiplex_operator
from btfcore.dome import Device

__all__ = [
    "PLAN_SCHEMA",
    "STRATEGIES",
    "CapturePlan",
    "ExposureModel",
    "Shot",
    "bootstrap_quadrants",
    "bootstrapping_plan",
    "full_single_light_plan",
    "multiplexed_plan",
    "multiplexing_gain",
    "patterns_plan",
    "sparse_multiplexed_plan",
    "sparse_plan",
    "validate_plan",
]

#: Schema name and version of the plan's dict form (:meth:`CapturePlan.to_dict`).
PLAN_SCHEMA: tuple[str, str] = ("btf-plan", "1.0")
#: Strategy names a plan may carry.
STRATEGIES: tuple[str, ...] = (
    "full-single", "sparse", "multiplexed", "sparse-multiplexed", "bootstrapping", "patterns", "custom",
)


# --------------------------------------------------------------------------- exposure


@dataclass(frozen=True)
class ExposureModel:
    """Shutter times of a pattern with ``m`` LEDs on.

    Parameters
    ----------
    single_ms : tuple of float
        Exposure bracket of a single-LED shot, milliseconds, strictly
        increasing (e.g. VMV Table 2, leather: 10, 144.2, 2080.1, 30000).
    exponent : float
        Brightness model: a pattern with ``m`` LEDs on is taken to be
        ``m ** exponent`` times as bright as one LED, so its bracket is the
        single-light bracket divided by ``m ** exponent`` (1: light adds up
        linearly and every step shrinks alike; 0: no shortening).
    min_shutter_ms : float
        Shortest shutter the cameras accept; shorter scaled times are raised
        to it, and steps that then coincide are merged (fewer exposure steps).
    measured_ms : mapping of int to tuple of float, optional
        Brackets measured for patterns with exactly ``m`` LEDs on; they take
        precedence over the scaling (e.g. ``{100: (30.0,)}`` for leather under
        the order-199 S-matrix, VMV Table 2).

    Notes
    -----
    For a pattern with :math:`m` LEDs on and single-light bracket
    :math:`t_1 < \\dots < t_K`,

    .. math:: t_k(m) = \\max\\left(t_k / m^{\\gamma},\\; t_{min}\\right)

    with duplicates removed. This is the first-order model of the thesis
    ("the larger amount of light reaching the material samples ... makes it
    possible to reduce total acquisition times", VMV §5.2). It ignores that
    multiplexing also compresses the dynamic range (shadows are lit by other
    LEDs), which lets a real operator drop exposure steps: VMV Table 2 used 1-2
    steps for the order-199 patterns where 4 were needed for single lights,
    and shutter times ~1000x shorter (at 10 dB less gain) for leather, far more
    than ``1/m = 1/100``. Give ``measured_ms`` where brackets were measured.
    """

    single_ms: tuple[float, ...] = (10.0, 100.0, 1000.0)
    exponent: float = 1.0
    min_shutter_ms: float = 0.1
    measured_ms: Mapping[int, tuple[float, ...]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "single_ms", _bracket(self.single_ms, "ExposureModel.single_ms"))
        measured = {}
        for m, times in dict(self.measured_ms).items():
            if isinstance(m, bool) or int(m) != m or int(m) < 1:
                raise ValueError(f"ExposureModel.measured_ms key {m!r} must be a number of LEDs >= 1")
            measured[int(m)] = _bracket(times, f"ExposureModel.measured_ms[{m}]")
        object.__setattr__(self, "measured_ms", measured)
        if not (math.isfinite(self.exponent) and self.exponent >= 0):
            raise ValueError(f"ExposureModel.exponent must be finite and >= 0, got {self.exponent}")
        if not (math.isfinite(self.min_shutter_ms) and self.min_shutter_ms > 0):
            raise ValueError(f"ExposureModel.min_shutter_ms must be finite and > 0, got {self.min_shutter_ms}")

    def bracket_ms(self, m: int) -> tuple[float, ...]:
        """Shutter times of a pattern with ``m`` LEDs on, milliseconds.

        Parameters
        ----------
        m : int
            LEDs on, >= 1.

        Returns
        -------
        times : tuple of float
            Strictly increasing shutter times.
        """
        if isinstance(m, bool) or int(m) != m or m < 1:
            raise ValueError(f"a pattern needs at least one LED on, got m = {m!r}")
        m = int(m)
        if m in self.measured_ms:
            return self.measured_ms[m]
        if m == 1:
            return self.single_ms
        scaled = [max(t / m ** self.exponent, self.min_shutter_ms) for t in self.single_ms]  # eq. t_k / m^g
        out: list[float] = []
        for t in scaled:
            if not out or t > out[-1] * (1 + 1e-9):
                out.append(float(t))
        return tuple(out)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (``measured_ms`` keys become strings)."""
        return {"single_ms": list(self.single_ms), "exponent": float(self.exponent),
                "min_shutter_ms": float(self.min_shutter_ms),
                "measured_ms": {str(k): list(v) for k, v in sorted(self.measured_ms.items())}}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "ExposureModel":
        """Inverse of :meth:`to_dict`."""
        return cls(single_ms=tuple(d["single_ms"]), exponent=float(d.get("exponent", 1.0)),
                   min_shutter_ms=float(d.get("min_shutter_ms", 0.1)),
                   measured_ms={int(k): tuple(v) for k, v in d.get("measured_ms", {}).items()})


def _bracket(times: Iterable[float], name: str) -> tuple[float, ...]:
    try:
        t = tuple(float(v) for v in times)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a sequence of shutter times in ms, got {times!r}") from None
    if not t:
        raise ValueError(f"{name} is empty; give at least one shutter time in ms")
    if not all(math.isfinite(v) and v > 0 for v in t):
        raise ValueError(f"{name} must be finite and > 0 ms, got {list(t)}")
    if any(b <= a for a, b in zip(t, t[1:])):
        raise ValueError(f"{name} must be strictly increasing, got {list(t)}; sort the bracket")
    return t


# --------------------------------------------------------------------------- plan


@dataclass(frozen=True)
class Shot:
    """One illumination pattern at one turntable position, one exposure bracket.

    Parameters
    ----------
    turntable : int
        Turntable position index into ``Device.turntable_angle_deg``.
    leds : tuple of int
        LEDs on, sorted, unique (a single-light shot has one).
    cameras : tuple of int
        Cameras that capture the shot, sorted, unique.
    shutter_ms : tuple of float
        Exposure bracket, milliseconds, strictly increasing; its length is the
        number of exposure steps.
    group : str
        Which part of the strategy the shot belongs to, e.g. ``"single"``,
        ``"S199"`` or ``"q2-S47"`` (the S-matrix order of a multiplexed group).
    """

    turntable: int
    leds: tuple[int, ...]
    cameras: tuple[int, ...]
    shutter_ms: tuple[float, ...]
    group: str = ""

    def __post_init__(self) -> None:
        if isinstance(self.turntable, bool) or int(self.turntable) != self.turntable:
            raise ValueError(f"Shot.turntable must be an integer index, got {self.turntable!r}")
        object.__setattr__(self, "turntable", int(self.turntable))
        for name in ("leds", "cameras"):
            ids = tuple(int(v) for v in getattr(self, name))
            if not ids:
                raise ValueError(f"Shot.{name} is empty; a shot needs at least one")
            if len(set(ids)) != len(ids):
                raise ValueError(f"Shot.{name} lists an id twice: {list(ids)}")
            object.__setattr__(self, name, tuple(sorted(ids)))
        object.__setattr__(self, "shutter_ms", _bracket(self.shutter_ms, "Shot.shutter_ms"))
        object.__setattr__(self, "group", str(self.group))

    @property
    def n_exposures(self) -> int:
        """Exposure steps of the bracket."""
        return len(self.shutter_ms)

    @property
    def n_leds_on(self) -> int:
        """LEDs on in the pattern."""
        return len(self.leds)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form."""
        return {"turntable": self.turntable, "leds": list(self.leds), "cameras": list(self.cameras),
                "shutter_ms": list(self.shutter_ms), "group": self.group}


@dataclass(frozen=True, eq=False)
class CapturePlan:
    """An ordered acquisition plan for one device.

    Parameters
    ----------
    device : str
        Name of the device the plan was made for.
    n_turn, n_cam, n_leds : int
        The device's turntable positions, cameras and LEDs (checked against a
        :class:`Device` by :func:`validate_plan`).
    turntable_angle_deg : (n_turn,) tuple of float
        The device's turntable angles.
    strategy : str
        One of :data:`STRATEGIES`.
    shots : tuple of Shot
        In execution order.
    parameters : dict
        Strategy parameters, plain JSON (exposure model, selection size, ...).
    """

    device: str
    n_turn: int
    n_cam: int
    n_leds: int
    turntable_angle_deg: tuple[float, ...]
    strategy: str
    shots: tuple[Shot, ...]
    parameters: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "shots", tuple(self.shots))
        object.__setattr__(self, "turntable_angle_deg", tuple(float(a) for a in self.turntable_angle_deg))
        if self.strategy not in STRATEGIES:
            raise ValueError(f"CapturePlan.strategy {self.strategy!r} is unknown; choose one of "
                             f"{', '.join(STRATEGIES)}")
        if min(self.n_turn, self.n_cam, self.n_leds) < 1:
            raise ValueError(f"CapturePlan needs n_turn, n_cam, n_leds >= 1, got "
                             f"{self.n_turn}, {self.n_cam}, {self.n_leds}")
        if len(self.turntable_angle_deg) != self.n_turn:
            raise ValueError(f"CapturePlan.turntable_angle_deg has {len(self.turntable_angle_deg)} angles "
                             f"for n_turn = {self.n_turn}")
        for i, s in enumerate(self.shots):
            if not isinstance(s, Shot):
                raise ValueError(f"CapturePlan.shots[{i}] is a {type(s).__name__}, not a Shot")
        _check_ids(self.shots, self.n_turn, self.n_cam, self.n_leds, f"plan for {self.device!r}")

    # ------------------------------------------------------------------ summaries

    @property
    def n_shots(self) -> int:
        """Number of shots (illumination patterns x turntable positions captured)."""
        return len(self.shots)

    @property
    def n_exposures(self) -> int:
        """Exposure steps over all shots (each step fires all the shot's cameras)."""
        return sum(s.n_exposures for s in self.shots)

    @property
    def n_images(self) -> int:
        """LDR images written: exposure steps x cameras, over all shots."""
        return sum(s.n_exposures * len(s.cameras) for s in self.shots)

    def coverage(self) -> np.ndarray:
        """How often each (turntable, LED) pair is lit.

        Returns
        -------
        counts : (n_turn, n_leds) ndarray of int64
        """
        counts = np.zeros((self.n_turn, self.n_leds), dtype=np.int64)
        for s in self.shots:
            counts[s.turntable, list(s.leds)] += 1
        return counts

    def illumination(self, turntable: int, group: str | None = None) -> np.ndarray:
        """Binary pattern matrix of the shots at one turntable position.

        Parameters
        ----------
        turntable : int
            Turntable position index.
        group : str, optional
            Only the shots of this group.

        Returns
        -------
        patterns : (n_shots_t, n_leds) ndarray of uint8
            Rows in plan order: the ``illumination`` matrix a capture store
            holds and :func:`btfcore.capture.demultiplex.demultiplex` inverts.
        """
        rows = [s for s in self.shots if s.turntable == turntable and (group is None or s.group == group)]
        out = np.zeros((len(rows), self.n_leds), dtype=np.uint8)
        for i, s in enumerate(rows):
            out[i, list(s.leds)] = 1
        return out

    def groups(self) -> tuple[str, ...]:
        """Shot groups in order of first appearance."""
        return tuple(dict.fromkeys(s.group for s in self.shots))

    # ------------------------------------------------------------------ dict form

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (no file I/O; :mod:`tasks.plan` writes it)."""
        return {"schema": PLAN_SCHEMA[0], "schema_version": PLAN_SCHEMA[1], "device": self.device,
                "strategy": self.strategy, "n_turn": self.n_turn, "n_cam": self.n_cam,
                "n_leds": self.n_leds, "turntable_angle_deg": list(self.turntable_angle_deg),
                "parameters": self.parameters, "shots": [s.to_dict() for s in self.shots]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "CapturePlan":
        """Inverse of :meth:`to_dict`; a missing key or bad shot raises ValueError naming it."""
        missing = [k for k in ("device", "strategy", "n_turn", "n_cam", "n_leds", "turntable_angle_deg",
                               "shots") if k not in d]
        if missing:
            raise ValueError(f"plan is missing {', '.join(missing)}")
        shots = []
        for i, s in enumerate(d["shots"]):
            try:
                shots.append(Shot(turntable=s["turntable"], leds=tuple(s["leds"]), cameras=tuple(s["cameras"]),
                                  shutter_ms=tuple(s["shutter_ms"]), group=s.get("group", "")))
            except (KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"plan shot {i}: {exc}") from None
        return cls(device=str(d["device"]), n_turn=int(d["n_turn"]), n_cam=int(d["n_cam"]),
                   n_leds=int(d["n_leds"]), turntable_angle_deg=tuple(d["turntable_angle_deg"]),
                   strategy=str(d["strategy"]), shots=tuple(shots), parameters=dict(d.get("parameters", {})))


def _check_ids(shots: Sequence[Shot], n_turn: int, n_cam: int, n_leds: int, what: str) -> None:
    for i, s in enumerate(shots):
        if not 0 <= s.turntable < n_turn:
            raise ValueError(f"{what}: shot {i} uses turntable position {s.turntable}, but the device has "
                             f"positions 0..{n_turn - 1}; fix the plan or choose the right device")
        bad = [c for c in s.cameras if not 0 <= c < n_cam]
        if bad:
            raise ValueError(f"{what}: shot {i} uses camera(s) {bad}, but the device has cameras "
                             f"0..{n_cam - 1}; fix the plan or choose the right device")
        bad = [led for led in s.leds if not 0 <= led < n_leds]
        if bad:
            raise ValueError(f"{what}: shot {i} switches on LED(s) {bad}, but the device has LEDs "
                             f"0..{n_leds - 1}; fix the plan or choose the right device")


def validate_plan(plan: CapturePlan, device: Device) -> CapturePlan:
    """Check that ``device`` can execute ``plan``.

    Parameters
    ----------
    plan : CapturePlan
    device : Device

    Returns
    -------
    plan : CapturePlan
        The same plan, for chaining.

    Raises
    ------
    ValueError
        Naming the first shot index and the turntable position, camera or LED
        id the device does not have, or a turntable angle that differs.
    """
    _check_ids(plan.shots, device.n_turn, device.n_cam, device.n_leds, f"plan for device {device.name!r}")
    if plan.n_turn == device.n_turn and not np.allclose(plan.turntable_angle_deg, device.turntable_angle_deg):
        raise ValueError(f"plan turntable angles {list(plan.turntable_angle_deg)} differ from device "
                         f"{device.name!r} angles {device.turntable_angle_deg.tolist()}; re-plan for this device")
    return plan


# --------------------------------------------------------------------------- strategies


def _cameras(device: Device, cameras: Sequence[int] | None) -> tuple[int, ...]:
    cams = tuple(range(device.n_cam)) if cameras is None else tuple(int(c) for c in cameras)
    bad = [c for c in cams if not 0 <= c < device.n_cam]
    if bad or not cams:
        raise ValueError(f"cameras {bad or '[]'} are not cameras of device {device.name!r} "
                         f"(0..{device.n_cam - 1})")
    return cams


def _plan(device: Device, strategy: str, shots: list[Shot], parameters: dict[str, Any]) -> CapturePlan:
    return CapturePlan(device=device.name, n_turn=device.n_turn, n_cam=device.n_cam, n_leds=device.n_leds,
                       turntable_angle_deg=tuple(device.turntable_angle_deg.tolist()), strategy=strategy,
                       shots=tuple(shots), parameters=parameters)


def _turntables(device: Device, turntables: Sequence[int] | None) -> list[int]:
    ts = list(range(device.n_turn)) if turntables is None else [int(t) for t in turntables]
    bad = [t for t in ts if not 0 <= t < device.n_turn]
    if bad:
        raise ValueError(f"turntable positions {bad} are not positions of device {device.name!r} "
                         f"(0..{device.n_turn - 1})")
    return ts


def full_single_light_plan(device: Device, exposure: ExposureModel | None = None, *,
                           cameras: Sequence[int] | None = None) -> CapturePlan:
    """Every LED alone at every turntable position.

    Parameters
    ----------
    device : Device
    exposure : ExposureModel, optional
        Its single-light bracket is used for every shot (default
        :class:`ExposureModel` ()).
    cameras : sequence of int, optional
        Cameras that fire (default all).

    Returns
    -------
    plan : CapturePlan
        ``n_turn * n_leds`` shots, turntable-major; covers every
        (turntable, LED) pair exactly once.

    Notes
    -----
    The reference measurement of the thesis' DOME II: 12 turntable positions x
    198 LEDs = 2376 shots, 11 cameras each (VMV paper §5.1).
    """
    exposure = exposure or ExposureModel()
    cams = _cameras(device, cameras)
    shots = [Shot(t, (led,), cams, exposure.bracket_ms(1), "single")
             for t in range(device.n_turn) for led in range(device.n_leds)]
    return _plan(device, "full-single", shots, {"exposure": exposure.to_dict()})


def _as_pairs(selection, shape: tuple[int, int], names: tuple[str, str]) -> np.ndarray:
    """(turntable, index) pairs from an (n, 2) array or an (n_turn, n) boolean mask, validated."""
    sel = np.asarray(selection)
    if sel.dtype == np.bool_:
        if sel.shape != shape:
            raise ValueError(f"selection mask must have shape {shape} ({names[0]}, {names[1]}), got {sel.shape}")
        return np.argwhere(sel)
    if sel.ndim != 2 or sel.shape[1] != 2 or sel.shape[0] == 0:
        raise ValueError(f"selection must be a non-empty (n, 2) array of ({names[0]}, {names[1]}) pairs "
                         f"or a boolean mask of shape {shape}, got shape {sel.shape}")
    if not np.issubdtype(sel.dtype, np.integer):
        if not np.all(np.isfinite(sel)) or np.any(sel != np.round(sel)):
            raise ValueError(f"selection must hold integer ({names[0]}, {names[1]}) indices")
        sel = sel.astype(np.int64)
    for i, (a, b) in enumerate(sel.tolist()):
        if not 0 <= a < shape[0]:
            raise ValueError(f"selection pair {i}: {names[0]} {a} is out of range 0..{shape[0] - 1}")
        if not 0 <= b < shape[1]:
            raise ValueError(f"selection pair {i}: {names[1]} {b} is out of range 0..{shape[1] - 1}")
    flat = sel[:, 0] * shape[1] + sel[:, 1]
    uniq, first, counts = np.unique(flat, return_index=True, return_counts=True)
    if np.any(counts > 1):
        i = int(np.sort(first[counts > 1])[0])
        raise ValueError(f"selection pair {i} ({names[0]} {sel[i, 0]}, {names[1]} {sel[i, 1]}) is listed "
                         "more than once; remove the duplicate")
    return np.stack(np.divmod(uniq, shape[1]), axis=1)  # sorted turntable-major


def sparse_plan(device: Device, selection, exposure: ExposureModel | None = None, *,
                cameras: Sequence[int] | None = None) -> CapturePlan:
    """Single-light shots of selected (turntable, LED) pairs, all cameras.

    Parameters
    ----------
    device : Device
    selection : (n_s, 2) array_like of int or (n_turn, n_leds) ndarray of bool
        The (turntable position, LED) pairs to capture, e.g. from a
        condition-number optimised sampling.
    exposure : ExposureModel, optional
    cameras : sequence of int, optional
        Default all: a dome captures all cameras in parallel at no extra time.

    Returns
    -------
    plan : CapturePlan
        One shot per selected pair, turntable-major.

    Raises
    ------
    ValueError
        Naming the selection index of an out-of-range or repeated pair.

    Notes
    -----
    Paper 4, §5: the sampling chooses "only from pairs of light sources and
    turntable rotations and then always use[s] all cameras available", so the
    acquisition time is :math:`n_s / (198 \\cdot 12)` of the full one.
    """
    exposure = exposure or ExposureModel()
    cams = _cameras(device, cameras)
    pairs = _as_pairs(selection, (device.n_turn, device.n_leds), ("turntable", "LED"))
    shots = [Shot(int(t), (int(led),), cams, exposure.bracket_ms(1), "single") for t, led in pairs]
    return _plan(device, "sparse", shots, {"exposure": exposure.to_dict(), "n_selected": int(len(pairs))})


def multiplexed_plan(device: Device, exposure: ExposureModel | None = None, *,
                     cameras: Sequence[int] | None = None,
                     turntables: Sequence[int] | None = None) -> CapturePlan:
    """S-matrix patterns over all the device's LEDs at every turntable position.

    Parameters
    ----------
    device : Device
    exposure : ExposureModel, optional
        Bracket per pattern from its number of LEDs on.
    cameras : sequence of int, optional
    turntables : sequence of int, optional
        Positions to capture (default all).

    Returns
    -------
    plan : CapturePlan
        ``n * n_turn`` shots with ``n = smallest_s_matrix_order(n_leds)``;
        the shots at one position are the rows of
        :func:`btfcore.acquisition.hadamard.multiplexing_patterns`, in order (group
        ``"S<n>"``).

    Notes
    -----
    198 LEDs -> order 199, 100 (or 99 where the truncated column was on) LEDs
    per pattern (VMV paper §5.1).
    """
    exposure = exposure or ExposureModel()
    cams = _cameras(device, cameras)
    pat = multiplexing_patterns(device.n_leds)
    group = f"S{pat.shape[0]}"
    rows = [tuple(np.flatnonzero(r).tolist()) for r in pat]
    shots = [Shot(t, leds, cams, exposure.bracket_ms(len(leds)), group)
             for t in _turntables(device, turntables) for leds in rows]
    return _plan(device, "multiplexed", shots, {"exposure": exposure.to_dict(), "s_matrix_order": pat.shape[0]})


def patterns_plan(device: Device, patterns: np.ndarray, exposure: ExposureModel | None = None, *,
                  cameras: Sequence[int] | None = None, turntables: Sequence[int] | None = None,
                  parameters: Mapping[str, Any] | None = None) -> CapturePlan:
    """Given binary LED patterns at every turntable position (e.g. basis-aware ones, issue 20).

    Parameters
    ----------
    device : Device
    patterns : (m, n_leds) array_like of 0/1
        One shot per pattern and position, in order; every pattern switches at least one LED on.
    exposure : ExposureModel, optional
        Bracket per pattern from its number of LEDs on.
    cameras, turntables : sequence of int, optional
    parameters : mapping, optional
        Recorded with the plan (besides ``exposure`` and ``n_patterns``).

    Returns
    -------
    plan : CapturePlan
        Strategy ``"patterns"``, ``m * n_turn`` shots of group ``"P<m>"``.
    """
    exposure = exposure or ExposureModel()
    cams = _cameras(device, cameras)
    p = np.asarray(patterns)
    if p.ndim != 2 or p.shape[1] != device.n_leds or not np.isin(p, (0, 1)).all():
        raise ValueError(f"patterns must be (m, {device.n_leds}) on/off values for device {device.name!r}, "
                         f"got shape {p.shape}")
    empty = np.flatnonzero(p.sum(axis=1) == 0)
    if p.shape[0] == 0 or empty.size:
        raise ValueError(f"pattern {int(empty[0]) if empty.size else 0} switches no LED on; drop it")
    group = f"P{p.shape[0]}"
    rows = [tuple(np.flatnonzero(r).tolist()) for r in p]
    shots = [Shot(t, leds, cams, exposure.bracket_ms(len(leds)), group)
             for t in _turntables(device, turntables) for leds in rows]
    return _plan(device, "patterns", shots, {**dict(parameters or {}), "exposure": exposure.to_dict(),
                                             "n_patterns": int(p.shape[0])})


def sparse_multiplexed_plan(device: Device, selection, exposure: ExposureModel | None = None, *,
                            select: str = "patterns", cameras: Sequence[int] | None = None) -> CapturePlan:
    """Sparse and multiplexed: selected S-matrix patterns, or S-matrices over selected LEDs.

    Parameters
    ----------
    device : Device
    selection : (n_s, 2) array_like of int or boolean mask
        With ``select="patterns"``: (turntable, S-matrix row) pairs, rows of
        ``multiplexing_patterns(device.n_leds)``, mask shape ``(n_turn, n)``.
        With ``select="leds"``: (turntable, LED) pairs, mask shape
        ``(n_turn, n_leds)``.
    exposure : ExposureModel, optional
    select : {'patterns', 'leds'}
        ``"patterns"``: paper 4, eq. 4 -- the measurement
        :math:`\\mathbf{S}\\mathbf{M}\\mathbf{B}` keeps the selected rows of the
        full multiplexed measurement, one shot per pair. ``"leds"``: at each
        turntable position the selected LEDs are multiplexed with their own
        S-matrix (``multiplexing_patterns(k)`` for ``k`` selected LEDs; a
        single selected LED is one single-light shot).
    cameras : sequence of int, optional

    Returns
    -------
    plan : CapturePlan

    Notes
    -----
    Paper 4, §5.4 used ``n_s = 400`` (pattern, turntable) pairs and reports
    12-22 min against 1.2-4 h for sparse single-light or full multiplexed
    acquisition.
    """
    exposure = exposure or ExposureModel()
    cams = _cameras(device, cameras)
    shots: list[Shot] = []
    if select == "patterns":
        pat = multiplexing_patterns(device.n_leds)
        pairs = _as_pairs(selection, (device.n_turn, pat.shape[0]), ("turntable", "pattern"))
        group = f"S{pat.shape[0]}"
        for t, r in pairs:
            leds = tuple(np.flatnonzero(pat[r]).tolist())
            shots.append(Shot(int(t), leds, cams, exposure.bracket_ms(len(leds)), group))
        params = {"select": select, "s_matrix_order": int(pat.shape[0])}
    elif select == "leds":
        pairs = _as_pairs(selection, (device.n_turn, device.n_leds), ("turntable", "LED"))
        orders = {}
        for t in np.unique(pairs[:, 0]).tolist():
            leds_t = pairs[pairs[:, 0] == t, 1]
            if len(leds_t) == 1:
                shots.append(Shot(t, (int(leds_t[0]),), cams, exposure.bracket_ms(1), "single"))
                orders[str(t)] = 1
                continue
            pat = multiplexing_patterns(len(leds_t))
            orders[str(t)] = int(pat.shape[0])
            for r in pat:
                leds = tuple(leds_t[np.flatnonzero(r)].tolist())
                shots.append(Shot(t, leds, cams, exposure.bracket_ms(len(leds)), f"S{pat.shape[0]}"))
        params = {"select": select, "s_matrix_order_per_turntable": orders}
    else:
        raise ValueError(f"select must be 'patterns' or 'leds', got {select!r}")
    params.update({"exposure": exposure.to_dict(), "n_selected": int(len(pairs))})
    return _plan(device, "sparse-multiplexed", shots, params)


def bootstrap_quadrants(device: Device, specular_half_width_deg: float = 45.0) -> np.ndarray:
    """Split the LED hemisphere into four azimuthal sectors, sector 0 opposite the cameras.

    Parameters
    ----------
    device : Device
        Its cameras must lie on one side (a semi-parallel dome, e.g. on one
        meridian): the horizontal resultant of their directions defines the
        camera azimuth :math:`\\phi_c`.
    specular_half_width_deg : float
        Half-width of sector 0 around :math:`\\phi_c + 180°`, in (0, 90); the
        other three share the rest equally. 45 gives four equal quadrants.

    Returns
    -------
    sector : (n_leds,) ndarray of int64
        0 for the LEDs opposite the cameras (mirror directions of the cameras,
        Fresnel effect), 1..3 counter-clockwise from there.

    Raises
    ------
    ValueError
        If the cameras surround the sample (no side opposite them), or the
        width is out of range.

    Notes
    -----
    VMV paper §4.2: "divide the hemisphere of light sources into quadrants of
    approximately equal size, such that one quadrant contains the light
    sources directly opposite the cameras". With relative azimuth
    :math:`\\delta = \\mathrm{wrap}(\\phi_l - \\phi_c - 180°) \\in [-180°, 180°)`
    and half-width :math:`w`: sector 0 if :math:`|\\delta| \\le w`, else
    :math:`1 + \\lfloor (\\delta + w \\bmod 360° - 2w) / ((360° - 2w)/3) \\rfloor`.
    """
    w = float(specular_half_width_deg)
    if not 0.0 < w < 90.0:
        raise ValueError(f"specular_half_width_deg must lie in (0, 90), got {w}")
    cam = device.camera_position / np.linalg.norm(device.camera_position, axis=1, keepdims=True)
    resultant = cam[:, :2].sum(axis=0)
    if np.linalg.norm(resultant) < 0.05 * device.n_cam:
        raise ValueError(f"the cameras of device {device.name!r} surround the sample (horizontal resultant "
                         f"{np.linalg.norm(resultant):.3f}); there is no LED quadrant opposite them, so "
                         "bootstrapping does not apply (VMV paper §4.2) -- use another strategy")
    phi_c = math.degrees(math.atan2(resultant[1], resultant[0]))
    phi_l = np.degrees(np.arctan2(device.led_position[:, 1], device.led_position[:, 0]))
    rel = (phi_l - phi_c - 180.0 + 180.0) % 360.0 - 180.0
    other = np.floor(((rel + w) % 360.0 - 2 * w) / ((360.0 - 2 * w) / 3.0)).astype(np.int64) + 1
    return np.where(np.abs(rel) <= w, 0, np.clip(other, 1, 3)).astype(np.int64)


def bootstrapping_plan(device: Device, exposure: ExposureModel | None = None, *,
                       specular_half_width_deg: float = 45.0,
                       cameras: Sequence[int] | None = None) -> CapturePlan:
    """Database bootstrapping: specular quadrant single-light, the other quadrants multiplexed.

    Parameters
    ----------
    device : Device
    exposure : ExposureModel, optional
        Single-light bracket for sector 0 and the bracket of each quadrant's
        patterns from their number of LEDs on.
    specular_half_width_deg : float
        See :func:`bootstrap_quadrants`.
    cameras : sequence of int, optional

    Returns
    -------
    plan : CapturePlan
        Per turntable position: the sector-0 LEDs one by one (group
        ``"q0-single"``), then for each sector ``k = 1..3`` the rows of
        ``multiplexing_patterns(len(sector_k))`` mapped to its LEDs (group
        ``"q<k>-S<n_k>"``). Every (turntable, LED) pair is lit at least once.

    Notes
    -----
    VMV paper §4.2 and §5.1: for the thesis' leathers the three multiplexed
    quadrants used S-matrices of order 47; the acquisition took about 9 h
    instead of almost 24 h (§5.3).
    """
    exposure = exposure or ExposureModel()
    cams = _cameras(device, cameras)
    sector = bootstrap_quadrants(device, specular_half_width_deg)
    parts: list[tuple[str, list[tuple[int, ...]]]] = []
    spec = np.flatnonzero(sector == 0)
    if spec.size:
        parts.append(("q0-single", [(int(led),) for led in spec]))
    orders = {}
    for k in (1, 2, 3):
        leds_k = np.flatnonzero(sector == k)
        if leds_k.size == 0:
            continue
        if leds_k.size == 1:
            parts.append((f"q{k}-single", [(int(leds_k[0]),)]))
            orders[str(k)] = 1
            continue
        pat = multiplexing_patterns(int(leds_k.size))
        orders[str(k)] = int(pat.shape[0])
        parts.append((f"q{k}-S{pat.shape[0]}", [tuple(leds_k[np.flatnonzero(r)].tolist()) for r in pat]))
    shots = [Shot(t, leds, cams, exposure.bracket_ms(len(leds)), group)
             for t in range(device.n_turn) for group, rows in parts for leds in rows]
    params = {"exposure": exposure.to_dict(), "specular_half_width_deg": float(specular_half_width_deg),
              "sector_sizes": np.bincount(sector, minlength=4).tolist(), "s_matrix_orders": orders}
    return _plan(device, "bootstrapping", shots, params)


# --------------------------------------------------------------------------- predicted multiplexing gain


def _exposure_gain_of(m: int, shutter_ms: Sequence[float], x_e: float, t_ref: float,
                      full_well_e: float) -> tuple[float, bool]:
    """``(t / t_ref, saturated)`` of the longest step of a bracket that keeps ``m`` LEDs of ``x_e``
    electrons each (at ``t_ref``) below the full well; the shortest step when every step saturates."""
    fits = [t for t in shutter_ms if m * x_e * t / t_ref <= full_well_e]
    if fits:
        return max(fits) / t_ref, False
    return min(shutter_ms) / t_ref, True


def multiplexing_gain(plan: CapturePlan, *, full_well_e: float, read_noise_e: float,
                      signal_fraction: float = 0.8,
                      single_ms: Sequence[float] | None = None) -> dict[str, Any] | None:
    """Predicted SNR of a plan's multiplexed shots over single-light capture, photon + read noise.

    Parameters
    ----------
    plan : CapturePlan
    full_well_e : float
        Full-well capacity of the device's sensor, electrons (> 0).
    read_noise_e : float
        Read-noise standard deviation, electrons (>= 0).
    signal_fraction : float
        Signal of the texel considered: under one LED at the longest
        single-light shutter time it collects ``signal_fraction * full_well_e``
        electrons, in (0, 1]. The default 0.8 is the auto exposure of
        :class:`btfcore.acquisition.noise.SensorNoise` (``fill``); darker
        texels (small fractions, read noise dominant) favour multiplexing.
    single_ms : sequence of float, optional
        The single-light bracket, ms; default the plan's exposure model
        (``plan.parameters["exposure"]["single_ms"]``).

    Returns
    -------
    report : dict or None
        None when no shot has more than one LED on. Otherwise plain JSON:
        ``gain`` (r.m.s. noise of single-light capture over that of the
        demultiplexed result, both in single-light radiance units; > 1 means
        multiplexing wins), ``loses`` (``gain < 1``), ``groups`` (gain per shot
        group), ``saturated_patterns`` (patterns of which every bracket step
        saturates at this signal), and the model inputs.

    Raises
    ------
    ValueError
        If the single-light bracket is neither given nor in the plan's
        parameters, or the sensor figures or ``signal_fraction`` are out of range.

    Notes
    -----
    Every LED lights the texel alike: :math:`x` electrons at the longest
    single-light shutter :math:`T_1` (:math:`x = f\\,\\mathrm{FW}`). A pattern
    :math:`i` with :math:`m_i` LEDs on and bracket :math:`t_{i,1} < \\dots`
    is read from its longest unsaturated step, :math:`t_i = \\max\\{t_{i,k} :
    m_i x t_{i,k} / T_1 \\le \\mathrm{FW}\\}` (HDR merge), so in units of
    the single-light signal its exposure gain is :math:`g_i = t_i / T_1` and
    its variance (:mod:`btfcore.acquisition.noise`)

    .. math:: \\sigma_i^2 = \\frac{m_i x}{g_i} + \\frac{\\sigma_r^2}{g_i^2}.

    With :math:`P` the least-squares demultiplexing operator of the shots'
    pattern matrix at one turntable position and group
    (:func:`btfcore.capture.demultiplex.demultiplex_operator`),
    :math:`\\operatorname{Var}(\\hat x_l) = \\sum_i P_{li}^2 \\sigma_i^2`, and
    the single-light image has :math:`\\sigma_1^2 = x + \\sigma_r^2`:

    .. math:: g = \\sqrt{\\sigma_1^2 \\,/\\, \\overline{\\operatorname{Var}(\\hat x)}}

    averaged over the multiplexed LEDs of all positions. At equal exposure
    (:math:`g_i = 1`, no step saturated) this is
    :func:`btfcore.capture.demultiplex.noise_gain`. With every step shortened
    by :math:`m` (the default :class:`ExposureModel`, :math:`g_i = 1/m`),
    :math:`\\sigma_i^2 = m^2 \\sigma_1^2` and an S-matrix of order :math:`n`
    (:math:`m = (n+1)/2`) gives :math:`g \\approx 1/\\sqrt{n+1}` whatever
    the signal: the same electrons per image, shared by :math:`m` LEDs
    (docs/acquisition-planning.md, "Multiplexing gain").
    """
    fw, sr, f = float(full_well_e), float(read_noise_e), float(signal_fraction)
    if not (math.isfinite(fw) and fw > 0):
        raise ValueError(f"full_well_e must be finite and > 0 electrons, got {full_well_e!r}")
    if not (math.isfinite(sr) and sr >= 0):
        raise ValueError(f"read_noise_e must be finite and >= 0 electrons, got {read_noise_e!r}")
    if not (0 < f <= 1):
        raise ValueError(f"signal_fraction must lie in (0, 1] (a fraction of the full well), got {signal_fraction!r}")
    if not any(s.n_leds_on > 1 for s in plan.shots):
        return None
    if single_ms is None:
        exp = plan.parameters.get("exposure")
        if not isinstance(exp, Mapping) or "single_ms" not in exp:
            raise ValueError(f"plan for {plan.device!r} ({plan.strategy}) has no parameters.exposure.single_ms; "
                             "give the single-light bracket (single_ms) to predict the multiplexing gain")
        single_ms = exp["single_ms"]
    t_ref = max(_bracket(single_ms, "single_ms"))
    x = f * fw                                                             # electrons per LED at T_1
    var_single = x + sr * sr                                               # eq. sigma_1^2 = x + sigma_r^2
    per_group: dict[str, list[float]] = {}
    saturated = 0
    cache: dict[tuple, tuple[float, int]] = {}
    keys = dict.fromkeys((s.turntable, s.group) for s in plan.shots if s.n_leds_on > 1)
    for t, grp in keys:
        shots = [s for s in plan.shots if s.turntable == t and s.group == grp]
        leds = sorted({led for s in shots for led in s.leds})
        col = {led: j for j, led in enumerate(leds)}
        M = np.zeros((len(shots), len(leds)))
        for i, s in enumerate(shots):
            M[i, [col[led] for led in s.leds]] = 1.0
        key = (M.tobytes(), M.shape, tuple(s.shutter_ms for s in shots))
        if key not in cache:
            var_i = np.empty(len(shots))
            n_sat = 0
            for i, s in enumerate(shots):
                g, sat = _exposure_gain_of(s.n_leds_on, s.shutter_ms, x, t_ref, fw)
                n_sat += sat
                var_i[i] = s.n_leds_on * x / g + sr * sr / (g * g)        # eq. sigma_i^2 = m x / g + sigma_r^2 / g^2
            try:
                P = demultiplex_operator(M)
            except ValueError as exc:
                raise ValueError(f"plan for {plan.device!r}, turntable position {t}, group {grp!r}: {exc}") from None
            cache[key] = (float(np.sum((P * P) @ var_i)), n_sat)         # eq. sum_l Var(x_l) = sum_li P_li^2 sigma_i^2
        total, n_sat = cache[key]
        saturated += n_sat
        acc = per_group.setdefault(grp, [0.0, 0.0])
        acc[0] += total
        acc[1] += len(leds)
    var_all = sum(v[0] for v in per_group.values()) / sum(v[1] for v in per_group.values())
    gain = float(math.sqrt(var_single / var_all))                          # eq. g = sqrt(sigma_1^2 / mean Var)
    return {"gain": gain, "loses": bool(gain < 1.0),
            "groups": {g: float(math.sqrt(var_single / (v[0] / v[1]))) for g, v in per_group.items()},
            "saturated_patterns": int(saturated), "signal_fraction": f, "signal_e": x,
            "full_well_e": fw, "read_noise_e": sr, "single_reference_ms": t_ref}
