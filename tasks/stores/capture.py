"""Capture store: the on-disk form of one camera-dome capture.

A capture store is a Zarr v3 group following the schema ``"btf-capture"``
version ``"1.0"`` (documented in ``docs/capture-store.md``). It holds the raw
Bayer exposure brackets of every view under every illumination pattern, the
exposure times, the illumination patterns, the device geometry and
calibration, dark frames, resume markers and, for simulated captures, the
exact ground truth.

This module creates such stores, opens them (validating everything that is
cheap to validate and reporting *all* problems at once), and writes them in
whole chunks so that parallel writers never share a chunk and a killed run
resumes without redoing finished views (DESIGN §3, §5, §7).

Examples
--------
>>> store = create_capture_store("cap.zarr", meta)            # doctest: +SKIP
>>> for t, c in store.pending_views():                        # doctest: +SKIP
...     store.write_bracket(t, c, frames, exposure_time)
>>> store.mark_complete()                                     # doctest: +SKIP
>>> store = open_capture_store("cap.zarr")                    # doctest: +SKIP
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr
from zarr.core.buffer import default_buffer_prototype

import btfcore
from tasks.integrity import CorruptChunkError, chunk_files_exist, create_array, missing_problem, rerun_hint
from tasks.staging import begin_store, finish_store

__all__ = [
    "BAYER_PATTERNS",
    "LV_ORDER",
    "SCHEMA_NAME",
    "SCHEMA_VERSION",
    "UNITS",
    "CaptureMetadata",
    "CaptureStore",
    "CaptureStoreError",
    "Problem",
    "create_capture_store",
    "open_capture_store",
    "to_json_attr",
    "validate_capture_store",
    "write_chunk_aligned",
]

SCHEMA_NAME = "btf-capture"
SCHEMA_VERSION = "1.0"
BAYER_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
LV_ORDER = ["turntable", "camera", "light"]
UNITS = {"exposure_time": "s", "positions": "m", "turntable_angle": "deg"}
SOURCES = ("simulator", "ingest")
SENSOR_KEYS = ("gain_e_per_dn", "read_noise_e", "full_well_e", "dark_current_e_per_s")

#: Tolerance for orthonormality of rotations and unit length of directions.
ROTATION_TOL = 1e-6
#: Largest accepted condition number of a homography.
HOMOGRAPHY_MAX_COND = 1e12
#: How many offending indices a problem lists before summarising.
MAX_LISTED = 10

_STORE = "<store>"
_ATTRS = "attrs"


# --------------------------------------------------------------------------
# Problems and errors
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a capture store.

    Parameters
    ----------
    array : str
        Array path inside the store (``"raw"``, ``"truth/btf"``), ``"attrs"``
        for root attributes or ``"<store>"`` for the store as a whole.
    index : str or None
        Offending index, attribute key or axis, e.g. ``"(t, c, i)=(1, 0, 2)"``.
    expected : str
        What the schema requires.
    found : str
        What the store holds.
    hint : str
        What to do about it.
    """

    array: str
    index: str | None
    expected: str
    found: str
    hint: str

    def __str__(self) -> str:
        where = self.array if self.index is None else f"{self.array}[{self.index}]"
        return f"{where}: expected {self.expected}; found {self.found}. Fix: {self.hint}"


class CaptureStoreError(ValueError):
    """A capture store (or the metadata for one) violates the schema.

    Parameters
    ----------
    path : str
        Store path or URL.
    problems : list of Problem
        Every problem found, not only the first.
    """

    def __init__(self, path: Any, problems: Sequence[Problem]) -> None:
        self.path = str(path)
        self.problems: list[Problem] = list(problems)
        super().__init__(self._format())

    def _format(self) -> str:
        n = len(self.problems)
        head = (
            f"capture store {self.path!r} ({SCHEMA_NAME} {SCHEMA_VERSION}) has "
            f"{n} problem{'s' if n != 1 else ''}:"
        )
        return "\n".join([head] + [f"  - {self.path}: {p}" for p in self.problems])

    def __reduce__(self):  # picklable across Dask / Prefect process boundaries
        return (type(self), (self.path, self.problems))


# --------------------------------------------------------------------------
# JSON attributes
# --------------------------------------------------------------------------


def to_json_attr(value: Any, where: str = "attrs") -> Any:
    """Convert a value into plain JSON for Zarr attributes.

    numpy scalars and arrays become Python numbers and lists, tuples become
    lists. NaN and infinities are refused, since they serialise to
    non-standard JSON (DESIGN §5).

    Parameters
    ----------
    value : Any
        Nested dicts / lists / tuples of str, bool, int, float, None and numpy
        scalars or arrays.
    where : str
        Key path used in error messages.

    Returns
    -------
    Any
        A value that :func:`json.dumps` accepts with ``allow_nan=False``.

    Raises
    ------
    ValueError
        For NaN / Inf, naming the key path.
    TypeError
        For values that have no JSON form, naming the key path.
    """
    if isinstance(value, np.ndarray):
        return [to_json_attr(v, f"{where}[{k}]") for k, v in enumerate(value.tolist())]
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(
                f"{where} is {value!r}; attributes must be finite JSON numbers "
                "(store null for unknown values)"
            )
        return float(value)
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"{where} has a non-string key {k!r}; JSON keys must be str")
            out[k] = to_json_attr(v, f"{where}[{k!r}]")
        return out
    if isinstance(value, (list, tuple)):
        return [to_json_attr(v, f"{where}[{k}]") for k, v in enumerate(value)]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"{where} is a {type(value).__name__}, which has no JSON form")


# --------------------------------------------------------------------------
# Metadata
# --------------------------------------------------------------------------


@dataclass(eq=False)
class CaptureMetadata:
    """Everything about a capture except the frames.

    Parameters
    ----------
    device : str
        Device name.
    bayer_pattern : {"RGGB", "BGGR", "GRBG", "GBRG"}
        The 2x2 top-left block of the raw frame, read row-major.
    black_level, white_level, bit_depth : int
        Sensor black level and saturation level in DN, ADC bit depth.
    sensor : dict
        ``gain_e_per_dn``, ``read_noise_e``, ``full_well_e``,
        ``dark_current_e_per_s``: floats, or None where unknown.
    sample_size_m : float
        Side of the square material sample in metres.
    texture_shape : (2,) tuple of int
        ``(h, w)`` of the rectified texture.
    illumination : (n_illum, n_leds) ndarray of {0, 1}
        LED on/off pattern of each illumination.
    led_position : (n_leds, 3) ndarray
        LED positions in metres, world frame (z up, sample centre at origin).
    camera_K : (n_cam, 3, 3) ndarray
        Intrinsics for the raw frame's pixel grid (the ROI).
    camera_R : (n_cam, 3, 3) ndarray
        World -> camera rotations.
    camera_t : (n_cam, 3) ndarray
        World -> camera translations in metres.
    turntable_angle : (n_turn,) ndarray
        Turntable angles in degrees.
    homography : (n_turn, n_cam, 3, 3) ndarray
        Sample-plane metric coordinates ``(x, y, 1)`` (metres, sample frame)
        to raw-frame pixels ``(col, row, 1)``.
    dark_exposure_time : (n_dark,) ndarray
        Exposure times of the dark frames in seconds, increasing.
    n_exp : int
        Exposures per bracket.
    roi_shape : (2,) tuple of int
        ``(rows, cols)`` of a raw frame.
    provenance : dict
        ``code_version``, ``config_hash``, ``seed``, ``created``, ``source``
        plus free extra keys (plain JSON).
    plan : dict, optional
        A capture executed from an acquisition plan: the plan's plain-JSON
        form (:meth:`btfcore.acquisition.plan.CapturePlan.to_dict`), kept in the store's
        ``plan`` group.
    plan_shot : (n_turn, n_cam, n_illum) ndarray of int, optional
        With ``plan``: the plan's shot index of each bracket ``(t, c, i)``,
        ``-1`` where the plan takes no such bracket (it is never written).
        Brackets of a plan capture may be shorter than ``n_exp``: their
        trailing exposure times are 0 (steps not taken).
    """

    device: str
    bayer_pattern: str
    black_level: int
    white_level: int
    bit_depth: int
    sensor: dict
    sample_size_m: float
    texture_shape: tuple[int, int]
    illumination: np.ndarray
    led_position: np.ndarray
    camera_K: np.ndarray
    camera_R: np.ndarray
    camera_t: np.ndarray
    turntable_angle: np.ndarray
    homography: np.ndarray
    dark_exposure_time: np.ndarray
    n_exp: int
    roi_shape: tuple[int, int]
    provenance: dict
    plan: dict | None = None
    plan_shot: np.ndarray | None = None

    @property
    def n_turn(self) -> int:
        return int(np.shape(self.turntable_angle)[0])

    @property
    def n_cam(self) -> int:
        return int(np.shape(self.camera_K)[0])

    @property
    def n_illum(self) -> int:
        return int(np.shape(self.illumination)[0])

    @property
    def n_leds(self) -> int:
        return int(np.shape(self.led_position)[0])

    @property
    def n_dark(self) -> int:
        return int(np.shape(self.dark_exposure_time)[0])

    @property
    def n_lv(self) -> int:
        return self.n_turn * self.n_cam * self.n_leds

    @property
    def raw_shape(self) -> tuple[int, int, int, int, int, int]:
        """``(n_turn, n_cam, n_illum, n_exp, rows, cols)``."""
        return (self.n_turn, self.n_cam, self.n_illum, int(self.n_exp), *map(int, self.roi_shape))

    @property
    def config_hash(self) -> str | None:
        return (self.provenance or {}).get("config_hash")


# Scalar attribute fields of CaptureMetadata and array fields (store name == field name).
_META_ATTR_FIELDS = (
    "device", "bayer_pattern", "black_level", "white_level", "bit_depth",
    "sensor", "sample_size_m", "texture_shape",
)
_META_ARRAY_FIELDS = (
    "illumination", "led_position", "camera_K", "camera_R", "camera_t",
    "turntable_angle", "homography", "dark_exposure_time",
)


# --------------------------------------------------------------------------
# Array specification
# --------------------------------------------------------------------------

# name -> (dtype, ((dimension_name, size_key), ...), chunk rule)
# chunk rule: None -> one chunk for the whole array; otherwise a tuple where an
# int is a fixed chunk length and a str is the size key (full axis).
_F3 = ("3", "3")
_ARRAYS: dict[str, tuple[str, tuple[tuple[str, str], ...], tuple | None]] = {
    "raw": (
        "uint16",
        (("turntable", "turntable"), ("camera", "camera"), ("illumination", "illumination"),
         ("exposure", "exposure"), ("row", "row"), ("col", "col")),
        (1, 1, 1, "exposure", "row", "col"),
    ),
    "exposure_time": (
        "float64",
        (("turntable", "turntable"), ("camera", "camera"), ("illumination", "illumination"),
         ("exposure", "exposure")),
        (1, 1, "illumination", "exposure"),
    ),
    "written": (
        "uint8",
        (("turntable", "turntable"), ("camera", "camera"), ("illumination", "illumination")),
        (1, 1, "illumination"),
    ),
    "turntable_angle": ("float64", (("turntable", "turntable"),), None),
    "homography": (
        "float64",
        (("turntable", "turntable"), ("camera", "camera"), ("i", "3"), ("j", "3")),
        None,
    ),
    "camera_K": ("float64", (("camera", "camera"), ("i", "3"), ("j", "3")), None),
    "camera_R": ("float64", (("camera", "camera"), ("i", "3"), ("j", "3")), None),
    "camera_t": ("float64", (("camera", "camera"), ("xyz", "3")), None),
    "illumination": ("uint8", (("illumination", "illumination"), ("led", "led")), None),
    "led_position": ("float64", (("led", "led"), ("xyz", "3")), None),
    "dark_frames": (
        "uint16",
        (("camera", "camera"), ("dark", "dark"), ("row", "row"), ("col", "col")),
        (1, "dark", "row", "col"),
    ),
    "dark_exposure_time": ("float64", (("dark", "dark"),), None),
    "dark_written": ("uint8", (("camera", "camera"),), (1,)),
}
_TRUTH_ARRAYS: dict[str, tuple[str, tuple[tuple[str, str], ...], tuple | None]] = {
    "truth/btf": (
        "float32",
        (("lv", "lv"), ("tex_row", "tex_row"), ("tex_col", "tex_col"), ("channel", "3")),
        ("led", "tex_row", "tex_col", "3"),
    ),
    "truth/btf_2x": (
        "float32",
        (("lv", "lv"), ("tex2_row", "tex2_row"), ("tex2_col", "tex2_col"), ("channel", "3")),
        ("led", "tex2_row", "tex2_col", "3"),
    ),
    "truth/light_dir": ("float64", (("lv", "lv"), ("xyz", "3")), None),
    "truth/view_dir": ("float64", (("lv", "lv"), ("xyz", "3")), None),
    "truth/lv_index": ("int32", (("lv", "lv"), ("field", "3")), None),
    "truth/written": ("uint8", (("turntable", "turntable"), ("camera", "camera")), (1, 1)),
}
_FIXED_SIZES = {"3": 3}


def _expected_chunks(rule: tuple | None, shape: tuple[int, ...], sizes: Mapping[str, int]):
    if rule is None:
        return tuple(max(1, int(s)) for s in shape)
    out = []
    for r, s in zip(rule, shape):
        if isinstance(r, int):
            out.append(r)
        else:
            out.append(max(1, int(sizes.get(r, _FIXED_SIZES.get(r, s)))))
    return tuple(out)


# --------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------


def _fmt_idx(idx: Sequence[int]) -> str:
    return "(" + ", ".join(str(int(i)) for i in idx) + ")"


def _listing(indices: np.ndarray, limit: int = MAX_LISTED) -> str:
    """Format the first ``limit`` rows of an ``(n, ndim)`` index array."""
    n = len(indices)
    shown = ", ".join(_fmt_idx(i) for i in indices[:limit])
    return shown + (f" (+{n - limit} more, {n} in all)" if n > limit else "")


def _nonfinite(name: str, arr: np.ndarray, axes: str, hint: str) -> list[Problem]:
    bad = ~np.isfinite(arr)
    if not bad.any():
        return []
    idx = np.argwhere(bad)
    return [Problem(
        name, f"{axes}={_listing(idx, 5)}", "finite values",
        f"{len(idx)} NaN/Inf value(s)", hint,
    )]


@dataclass
class _Info:
    """What validation needs to know about one array, without its data."""

    shape: tuple[int, ...]
    dtype: str
    chunks: tuple[int, ...] | None
    dims: tuple[str, ...] | None
    load: Callable[[], np.ndarray] | None  # None: do not read (big or not yet there)


class _Sizes:
    """Axis lengths taken from the first array that has them."""

    def __init__(self) -> None:
        self.value: dict[str, int] = dict(_FIXED_SIZES)
        self.source: dict[str, str] = {k: "the schema" for k in _FIXED_SIZES}

    def seed(self, key: str, n: int, source: str) -> None:
        self.value[key] = int(n)
        self.source[key] = source

    def see(self, key: str, n: int, array: str, axis: int, dim: str, problems: list[Problem]) -> bool:
        if key not in self.value:
            self.seed(key, n, f"{array} axis {axis}")
            return True
        if self.value[key] != n:
            problems.append(Problem(
                array, f"axis {axis} ({dim})",
                f"length {self.value[key]} to match {self.source[key]}",
                f"length {n}",
                f"{array} and {self.source[key].split(' axis')[0]} disagree on the number of "
                f"{dim} entries; check the device calibration / manifest that produced them "
                "and recreate the store",
            ))
            return False
        return True


def _check_attrs(attrs: Mapping[str, Any], problems: list[Problem], *, in_memory: bool = False) -> None:
    """Root attribute checks (shared by stores and in-memory metadata)."""
    P = problems.append
    recreate = "recreate the store with btf-pipeline (create_capture_store)"

    def get(key):
        if key not in attrs:
            P(Problem(_ATTRS, key, f"attribute {key!r}", "nothing",
                      f"the store is missing root attribute {key!r}; {recreate}"))
            return None, False
        return attrs[key], True

    if not in_memory:
        v, ok = get("schema")
        if ok and v != SCHEMA_NAME:
            P(Problem(_ATTRS, "schema", repr(SCHEMA_NAME), repr(v),
                      "this is not a capture store; open it with the reader for its schema"))
        v, ok = get("schema_version")
        if ok and v != SCHEMA_VERSION:
            P(Problem(_ATTRS, "schema_version", repr(SCHEMA_VERSION), repr(v),
                      f"this code reads {SCHEMA_NAME} {SCHEMA_VERSION}; use the btf-pipeline "
                      "version that wrote the store or migrate it"))

    v, ok = get("device")
    if ok and (not isinstance(v, str) or not v):
        P(Problem(_ATTRS, "device", "a non-empty string", repr(v), "set the device name"))

    v, ok = get("bayer_pattern")
    if ok and v not in BAYER_PATTERNS:
        P(Problem(_ATTRS, "bayer_pattern", f"one of {', '.join(BAYER_PATTERNS)}", repr(v),
                  "give the 2x2 top-left block of the raw frame read row-major "
                  "(check the camera's CFA / LibRaw raw_pattern for the ROI origin)"))

    def is_int(x):
        return isinstance(x, int) and not isinstance(x, bool)

    levels = {}
    for key in ("black_level", "white_level", "bit_depth"):
        v, ok = get(key)
        if ok:
            if is_int(v):
                levels[key] = v
            else:
                P(Problem(_ATTRS, key, "an integer", repr(v), f"store {key} as an integer DN"))
    bd = levels.get("bit_depth")
    if bd is not None and not 1 <= bd <= 16:
        P(Problem(_ATTRS, "bit_depth", "1..16 (raw is uint16)", repr(bd),
                  "set the ADC bit depth of the sensor"))
        bd = None
    bl, wl = levels.get("black_level"), levels.get("white_level")
    if bl is not None and bl < 0:
        P(Problem(_ATTRS, "black_level", ">= 0", repr(bl), "check the sensor black level"))
    if bl is not None and wl is not None and bl >= wl:
        P(Problem(_ATTRS, "black_level", f"black_level < white_level ({wl})", repr(bl),
                  "check the sensor calibration: black level must lie below the saturation level"))
    if wl is not None and bd is not None and wl > 2**bd - 1:
        P(Problem(_ATTRS, "white_level", f"<= 2**bit_depth - 1 = {2**bd - 1}", repr(wl),
                  "check white_level and bit_depth against the camera's raw format"))

    v, ok = get("sensor")
    if ok:
        if not isinstance(v, Mapping):
            P(Problem(_ATTRS, "sensor", f"a dict with keys {list(SENSOR_KEYS)}", repr(v),
                      "store the sensor noise parameters (null where unknown)"))
        else:
            for k in SENSOR_KEYS:
                if k not in v:
                    P(Problem(_ATTRS, f"sensor.{k}", "a float or null", "nothing",
                              "add the key (null when unknown)"))
                    continue
                x = v[k]
                if x is None:
                    continue
                if (not isinstance(x, (int, float)) or isinstance(x, bool)
                        or not math.isfinite(x)):
                    P(Problem(_ATTRS, f"sensor.{k}", "a finite float or null", repr(x),
                              "store a calibrated value or null"))
                elif (x < 0) if k in ("read_noise_e", "dark_current_e_per_s") else (x <= 0):
                    P(Problem(_ATTRS, f"sensor.{k}",
                              ">= 0" if k in ("read_noise_e", "dark_current_e_per_s") else "> 0",
                              repr(x), "check the sensor calibration"))

    v, ok = get("sample_size_m")
    if ok and (not isinstance(v, (int, float)) or isinstance(v, bool)
               or not math.isfinite(v) or v <= 0):
        P(Problem(_ATTRS, "sample_size_m", "a positive number of metres", repr(v),
                  "set the side length of the square sample in metres"))

    v, ok = get("texture_shape")
    if ok and not (isinstance(v, (list, tuple)) and len(v) == 2
                   and all(is_int(x) and x > 0 for x in v)):
        P(Problem(_ATTRS, "texture_shape", "[h, w], two positive integers", repr(v),
                  "set the rectified texture size"))

    if not in_memory:
        v, ok = get("lv_order")
        if ok and not (isinstance(v, (list, tuple)) and list(v) == LV_ORDER):
            P(Problem(_ATTRS, "lv_order", repr(LV_ORDER), repr(v),
                      "light/view pairs must be flattened row-major over "
                      "(turntable, camera, light); recreate the store"))
        v, ok = get("units")
        if ok and not (isinstance(v, Mapping) and all(v.get(k) == u for k, u in UNITS.items())):
            P(Problem(_ATTRS, "units", repr(UNITS), repr(v),
                      "convert the arrays to these units and recreate the store"))
        v, ok = get("complete")
        if ok and not isinstance(v, bool):
            P(Problem(_ATTRS, "complete", "true or false", repr(v), recreate))

    v, ok = get("provenance")
    if ok:
        if not isinstance(v, Mapping):
            P(Problem(_ATTRS, "provenance", "a dict", repr(v), recreate))
        else:
            _check_provenance(v, problems)


def _check_provenance(prov: Mapping[str, Any], problems: list[Problem]) -> None:
    P = problems.append
    for key in ("code_version", "config_hash"):
        x = prov.get(key)
        if not isinstance(x, str) or not x:
            P(Problem(_ATTRS, f"provenance.{key}", "a non-empty string",
                      "nothing" if key not in prov else repr(x),
                      "the producing flow must record it (it keys resume and caches)"))
    if "seed" not in prov:
        P(Problem(_ATTRS, "provenance.seed", "an integer or null", "nothing",
                  "record the random seed (null for real captures)"))
    elif prov["seed"] is not None and (not isinstance(prov["seed"], int) or isinstance(prov["seed"], bool)):
        P(Problem(_ATTRS, "provenance.seed", "an integer or null", repr(prov["seed"]),
                  "record the random seed (null for real captures)"))
    created = prov.get("created")
    ok = isinstance(created, str)
    if ok:
        try:
            _dt.datetime.fromisoformat(created)
        except ValueError:
            ok = False
    if not ok:
        P(Problem(_ATTRS, "provenance.created", "an ISO 8601 timestamp",
                  "nothing" if "created" not in prov else repr(created),
                  "record the creation time, e.g. datetime.now(timezone.utc).isoformat()"))
    if prov.get("source") not in SOURCES:
        P(Problem(_ATTRS, "provenance.source", f"one of {list(SOURCES)}",
                  "nothing" if "source" not in prov else repr(prov.get("source")),
                  "say which stage produced the store"))


def _resume_hint(attrs: Mapping[str, Any]) -> str:
    prov = attrs.get("provenance") if isinstance(attrs.get("provenance"), Mapping) else {}
    src = prov.get("source")
    if src == "simulator":
        return ("re-run `btf simulate` with the same config to resume (finished views "
                "are kept), or open with require_complete=False")
    if src == "ingest":
        return ("re-run `btf ingest` with the same manifest to resume (finished views "
                "are kept), or open with require_complete=False")
    return "re-run the producing command with the same config to resume"


def _check_shapes(
    infos: Mapping[str, _Info], sizes: _Sizes, problems: list[Problem],
    *, check_layout: bool = True,
) -> dict[str, bool]:
    """Dtypes, dimensions, shapes and chunking; returns which arrays are usable."""
    usable: dict[str, bool] = {}
    spec_all = {**_ARRAYS, **_TRUTH_ARRAYS}
    order = list(_ARRAYS) + list(_TRUTH_ARRAYS)
    lv_seeded = False
    for name in order:
        if name not in infos:
            continue
        if name.startswith("truth/") and not lv_seeded:
            lv_seeded = True
            if all(k in sizes.value for k in ("turntable", "camera", "led")) and "lv" not in sizes.value:
                sizes.seed("lv", sizes.value["turntable"] * sizes.value["camera"] * sizes.value["led"],
                           "n_turn * n_cam * n_leds")
        info = infos[name]
        dtype, axes, chunk_rule = spec_all[name]
        if info.dtype != dtype:
            problems.append(Problem(
                name, None, f"dtype {dtype}", f"dtype {info.dtype}",
                f"write {name} as {dtype} (recreate the array / store)"))
        if len(info.shape) != len(axes):
            problems.append(Problem(
                name, None, f"{len(axes)} dimensions ({', '.join(a for a, _ in axes)})",
                f"shape {info.shape}", f"recreate {name} with the schema's layout"))
            usable[name] = False
            continue
        ok = True
        for ax, ((dim, key), n) in enumerate(zip(axes, info.shape)):
            ok &= sizes.see(key, n, name, ax, dim, problems)
        usable[name] = ok
        if check_layout:
            want_dims = tuple(a for a, _ in axes)
            if info.dims is not None and tuple(info.dims) != want_dims:
                problems.append(Problem(
                    name, "dimension_names", repr(list(want_dims)),
                    repr(list(info.dims)), f"recreate {name} with the schema's dimension names"))
            if info.chunks is not None:
                want = _expected_chunks(chunk_rule, info.shape, sizes.value)
                if tuple(info.chunks) != want:
                    problems.append(Problem(
                        name, "chunks", f"chunks {want}", f"chunks {tuple(info.chunks)}",
                        "writers own whole chunks of exactly this layout; recreate the store "
                        "with create_capture_store"))
    return usable


def _check_content(
    infos: Mapping[str, _Info], usable: Mapping[str, bool], sizes: _Sizes,
    attrs: Mapping[str, Any], problems: list[Problem], *, planned: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Value checks on the small arrays. Returns the loaded arrays.

    ``planned`` (a plan capture, :func:`plan_shots`): brackets may end in exposure times of 0
    (steps the plan does not take).
    """
    data: dict[str, np.ndarray] = {}
    # Resume markers first: writers put a view's data on disk before its marker,
    # so a store that other workers are still writing validates consistently.
    markers = [n for n in infos if n.endswith("written")]
    for name in markers + [n for n in infos if n not in markers]:
        info = infos[name]
        if usable.get(name) and info.load is not None:
            try:
                data[name] = np.asarray(info.load())
            except CorruptChunkError as e:             # a checksum mismatch / truncated chunk: named, not raised
                problems.append(Problem(name, f"chunk {e.chunk}", "a chunk that reads back as written",
                                        e.problem, e.hint))
    P = problems.append
    calib = "check the device calibration that produced it"

    # --- written markers --------------------------------------------------
    written = data.get("written")
    if written is not None:
        bad = ~np.isin(written, (0, 1))
        if bad.any():
            P(Problem("written", f"(t, c, i)={_listing(np.argwhere(bad))}", "0 or 1",
                      f"{int(bad.sum())} other value(s)",
                      "the resume markers are corrupt; recreate the store"))

    # --- exposure times (only where written) ------------------------------
    et = data.get("exposure_time")
    if et is not None:
        mask = np.ones(et.shape[:3], dtype=bool)
        if written is not None and written.shape == et.shape[:3]:
            mask = written == 1
        hint = ("exposure times must be > 0 s and strictly increasing within a bracket; "
                "check the manifest / EXIF exposure times for this bracket and re-write it")
        if planned is not None:
            et = trailing_steps_filled(et)
        fin = np.isfinite(et).all(axis=-1)
        nf = np.argwhere(mask & ~fin)
        if len(nf):
            P(Problem("exposure_time", f"(t, c, i)={_listing(nf)}", "finite exposure times",
                      f"NaN/Inf in {len(nf)} bracket(s)", hint))
        pos = (et > 0).all(axis=-1)
        nonpos = np.argwhere(mask & fin & ~pos)
        if len(nonpos):
            first = tuple(nonpos[0])
            P(Problem("exposure_time", f"(t, c, i)={_listing(nonpos)}", "all exposure times > 0 s",
                      f"{len(nonpos)} bracket(s) with a time <= 0, e.g. {et[first].tolist()} at "
                      f"{_fmt_idx(first)}", hint))
        with np.errstate(invalid="ignore"):
            inc = (np.diff(et, axis=-1) > 0).all(axis=-1)
        noninc = np.argwhere(mask & fin & pos & ~inc)
        if len(noninc):
            first = tuple(noninc[0])
            P(Problem("exposure_time", f"(t, c, i)={_listing(noninc)}",
                      "strictly increasing times along the exposure axis",
                      f"{len(noninc)} bracket(s) not increasing, e.g. {et[first].tolist()} at "
                      f"{_fmt_idx(first)}", hint))

    # --- illumination ---------------------------------------------------------
    il = data.get("illumination")
    if il is not None:
        bad = ~np.isin(il, (0, 1))
        if bad.any():
            P(Problem("illumination", f"(illum, led)={_listing(np.argwhere(bad))}",
                      "binary 0/1 LED states", f"{int(bad.sum())} other value(s)",
                      "store each pattern as LED on (1) / off (0); check the S-matrix / manifest"))
        empty = np.flatnonzero(~(il == 1).any(axis=1)) if il.ndim == 2 else []
        if len(empty):
            rows = ", ".join(str(int(r)) for r in empty[:MAX_LISTED])
            more = f" (+{len(empty) - MAX_LISTED} more)" if len(empty) > MAX_LISTED else ""
            P(Problem("illumination", f"row {rows}{more}", "at least one LED on per row",
                      f"{len(empty)} row(s) with no LED on",
                      "drop dark patterns from the illumination list (dark frames go to "
                      "dark_frames) or fix the pattern"))

    # --- LEDs -----------------------------------------------------------------
    lp = data.get("led_position")
    if lp is not None:
        problems += _nonfinite("led_position", lp, "(led, xyz)", calib)
        z = lp[:, 2]
        low = np.flatnonzero(np.isfinite(z) & (z <= 0))
        if len(low):
            P(Problem("led_position", f"led {', '.join(map(str, low[:MAX_LISTED].tolist()))}",
                      "z > 0 m (LEDs above the sample plane, z up)",
                      f"z = {z[low[:5]].tolist()}",
                      "positions must be in metres in the world frame with z up and the sample "
                      "centre at the origin; " + calib))

    # --- cameras --------------------------------------------------------------
    K = data.get("camera_K")
    if K is not None:
        problems += _nonfinite("camera_K", K, "(camera, i, j)", calib)
        for c in range(K.shape[0]):
            k = K[c]
            if not np.isfinite(k).all():
                continue
            if not (np.allclose(k[2], (0, 0, 1), atol=1e-9) and np.allclose(k[1, 0], 0)
                    and k[0, 0] > 0 and k[1, 1] > 0):
                P(Problem("camera_K", f"camera {c}",
                          "[[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0",
                          repr(np.round(k, 6).tolist()), calib))
    R = data.get("camera_R")
    if R is not None:
        problems += _nonfinite("camera_R", R, "(camera, i, j)", calib)
        for c in range(R.shape[0]):
            r = R[c]
            if not np.isfinite(r).all():
                continue
            err = float(np.abs(r @ r.T - np.eye(3)).max())
            det = float(np.linalg.det(r))
            if err > ROTATION_TOL or det <= 0:
                P(Problem("camera_R", f"camera {c}",
                          f"an orthonormal rotation (|R R^T - I| <= {ROTATION_TOL:g}, det = +1)",
                          f"|R R^T - I| = {err:.3g}, det = {det:.6g}",
                          "store the world->camera rotation matrix (re-orthonormalise it, e.g. "
                          "by SVD, or check the calibration's convention)"))
    ct = data.get("camera_t")
    if ct is not None:
        problems += _nonfinite("camera_t", ct, "(camera, xyz)", calib)
    ta = data.get("turntable_angle")
    if ta is not None:
        problems += _nonfinite("turntable_angle", ta, "(turntable,)", "check the manifest")

    # --- homographies -----------------------------------------------------
    H = data.get("homography")
    if H is not None:
        problems += _nonfinite("homography", H, "(t, c, i, j)", calib)
        s = attrs.get("sample_size_m")
        s = float(s) if isinstance(s, (int, float)) and not isinstance(s, bool) and s > 0 else None
        rows, cols = sizes.value.get("row"), sizes.value.get("col")
        singular, outside = [], []
        for t in range(H.shape[0]):
            for c in range(H.shape[1]):
                h = H[t, c]
                if not np.isfinite(h).all():
                    continue
                cond = np.linalg.cond(h)
                if not np.isfinite(cond) or cond > HOMOGRAPHY_MAX_COND:
                    singular.append(((t, c), cond))
                    continue
                if s is None or rows is None or cols is None:
                    continue
                corners = np.array([[-s / 2, -s / 2, 1], [s / 2, -s / 2, 1],
                                    [s / 2, s / 2, 1], [-s / 2, s / 2, 1]])
                q = corners @ h.T
                w = q[:, 2]
                if not (np.all(w > 0) or np.all(w < 0)):
                    outside.append(((t, c), "the sample plane crosses the horizon (w changes sign)"))
                    continue
                px = q[:, :2] / w[:, None]
                inside = ((px[:, 0] >= -0.5) & (px[:, 0] <= cols - 0.5)
                          & (px[:, 1] >= -0.5) & (px[:, 1] <= rows - 0.5))
                if not inside.all():
                    outside.append(((t, c), f"corners at (col, row) {np.round(px, 2).tolist()}"))
        if singular:
            P(Problem("homography", "(t, c)=" + ", ".join(_fmt_idx(i) for i, _ in singular[:MAX_LISTED])
                      + (f" (+{len(singular) - MAX_LISTED} more)" if len(singular) > MAX_LISTED else ""),
                      f"an invertible 3x3 matrix (condition number <= {HOMOGRAPHY_MAX_COND:g})",
                      f"condition number {singular[0][1]:.3g} at {_fmt_idx(singular[0][0])}",
                      "recompute the homography from the camera calibration and turntable "
                      "angle (H = K [r1 r2 t] in the sample frame)"))
        if outside:
            P(Problem("homography", "(t, c)=" + ", ".join(_fmt_idx(i) for i, _ in outside[:MAX_LISTED])
                      + (f" (+{len(outside) - MAX_LISTED} more)" if len(outside) > MAX_LISTED else ""),
                      f"the sample corners (+-s/2, +-s/2) with s = {s} m mapped inside the "
                      f"{rows}x{cols} raw frame",
                      f"{outside[0][1]} at {_fmt_idx(outside[0][0])}",
                      "check sample_size_m (metres), the ROI offset in camera_K / homography, "
                      "and that the homography maps sample (x, y) to raw (col, row)"))

    # --- dark frames -----------------------------------------------------
    dt = data.get("dark_exposure_time")
    if dt is not None:
        problems += _nonfinite("dark_exposure_time", dt, "(dark,)", "check the manifest")
        if np.isfinite(dt).all():
            if not (dt > 0).all():
                P(Problem("dark_exposure_time", f"dark {', '.join(map(str, np.flatnonzero(dt <= 0).tolist()))}",
                          "exposure times > 0 s", repr(dt.tolist()), "check the dark-frame exposure times"))
            elif not (np.diff(dt) > 0).all():
                P(Problem("dark_exposure_time", f"dark {', '.join(map(str, (np.flatnonzero(np.diff(dt) <= 0) + 1).tolist()))}",
                          "strictly increasing exposure times", repr(dt.tolist()),
                          "sort the dark frames by exposure time (one frame per time)"))
    dw = data.get("dark_written")
    if dw is not None and not np.isin(dw, (0, 1)).all():
        P(Problem("dark_written", None, "0 or 1", repr(dw.tolist()), "recreate the store"))

    # --- truth --------------------------------------------------------------
    ld, vd, li = data.get("truth/light_dir"), data.get("truth/view_dir"), data.get("truth/lv_index")
    if ld is not None and vd is not None and li is not None and _directions_written(ld, vd):
        for nm, d in (("truth/light_dir", ld), ("truth/view_dir", vd)):
            problems += _nonfinite(nm, d, "(lv, xyz)", "re-run the simulator")
            norm = np.linalg.norm(d, axis=-1)
            bad = np.flatnonzero(np.isfinite(norm) & (np.abs(norm - 1) > ROTATION_TOL))
            if len(bad):
                P(Problem(nm, f"lv {', '.join(map(str, bad[:MAX_LISTED].tolist()))}",
                          "unit vectors in the sample frame", f"norms {norm[bad[:5]].tolist()}",
                          "normalise the directions (re-run the simulator)"))
        want = _lv_index(sizes.value.get("turntable", 0), sizes.value.get("camera", 0),
                         sizes.value.get("led", 0))
        if want.shape == li.shape:
            bad = np.flatnonzero((li != want).any(axis=1))
            if len(bad):
                P(Problem("truth/lv_index", f"lv {', '.join(map(str, bad[:MAX_LISTED].tolist()))}",
                          "(turntable, camera, led) in row-major order (lv_order)",
                          f"{li[bad[0]].tolist()} at lv {bad[0]}",
                          "flatten light/view pairs row-major over (turntable, camera, led)"))
    return data


def trailing_steps_filled(et: np.ndarray) -> np.ndarray:
    """Exposure times with the trailing zeros of a plan capture's shorter brackets (steps not
    taken) replaced by increasing stand-ins, so that a bracket is valid iff its taken steps are
    finite, > 0 and strictly increasing and every step after the first zero is zero too."""
    et = np.asarray(et, dtype=np.float64)
    taken = et != 0
    trailing = np.flip(np.cumsum(np.flip(taken, -1), -1), -1) == 0   # no taken step from here on
    first_ok = taken[..., :1] if et.shape[-1] else taken
    trailing &= np.broadcast_to(first_ok, et.shape)                   # a bracket needs its first step
    with np.errstate(invalid="ignore"):
        top = np.nanmax(np.where(np.isfinite(et), np.abs(et), 0.0), axis=-1, keepdims=True) if et.size else et
    stand_in = top + 1.0 + np.arange(et.shape[-1])
    return np.where(trailing, stand_in, et)


def bracket_steps(et: np.ndarray) -> np.ndarray:
    """Exposure steps taken in each bracket: the leading times > 0 (a plan capture's shorter
    brackets end in zeros)."""
    et = np.asarray(et)
    return np.cumprod(et > 0, axis=-1).sum(axis=-1)


def _directions_written(ld: np.ndarray, vd: np.ndarray) -> bool:
    return bool(np.any(ld != 0) or np.any(vd != 0))


def _lv_index(n_turn: int, n_cam: int, n_leds: int) -> np.ndarray:
    """``(n_lv, 3)`` int32 (turntable, camera, led) in row-major order."""
    g = np.indices((n_turn, n_cam, n_leds)).reshape(3, -1).T
    return g.astype(np.int32)


def _check_completeness(
    data: Mapping[str, np.ndarray], attrs: Mapping[str, Any], sizes: _Sizes,
    problems: list[Problem], *, require_complete: bool, check_flag: bool = True,
    planned: np.ndarray | None = None,
) -> None:
    hint = _resume_hint(attrs)
    flagged = attrs.get("complete") is True
    missing_any = False
    w = data.get("written")
    if w is not None:
        todo = w != 1
        if planned is not None and planned.shape == w.shape:
            todo &= planned                                  # brackets the plan does not take are never written
        miss = np.argwhere(todo)
        if len(miss):
            missing_any = True
            if require_complete or flagged:
                P = Problem("written", f"(t, c, i)={_listing(miss)}",
                            "every bracket written",
                            f"{len(miss)} of {w.size} bracket(s) not written"
                            + (" although attrs['complete'] is true" if flagged else ""), hint)
                problems.append(P)
    dw = data.get("dark_written")
    if dw is not None and sizes.value.get("dark", 0) > 0:
        miss = np.flatnonzero(dw != 1)
        if len(miss):
            missing_any = True
            if require_complete or flagged:
                problems.append(Problem(
                    "dark_written", f"camera {', '.join(map(str, miss[:MAX_LISTED].tolist()))}",
                    "dark frames written for every camera",
                    f"{len(miss)} camera(s) without dark frames", hint))
    tw = data.get("truth/written")
    if tw is not None:
        miss = np.argwhere(tw != 1)
        if len(miss):
            missing_any = True
            if require_complete or flagged:
                problems.append(Problem(
                    "truth/written", f"(t, c)={_listing(miss)}", "ground truth written for every view",
                    f"{len(miss)} view(s) without ground truth", hint))
    ld, vd = data.get("truth/light_dir"), data.get("truth/view_dir")
    if ld is not None and vd is not None and not _directions_written(ld, vd):
        missing_any = True
        if require_complete or flagged:
            problems.append(Problem(
                "truth/light_dir", None, "ground-truth directions written",
                "all zeros (never written)", hint))
    if check_flag and require_complete and not flagged and not missing_any:
        problems.append(Problem(
            _ATTRS, "complete", "true", repr(attrs.get("complete")),
            "every bracket is written but the store was never marked complete: call "
            "CaptureStore.mark_complete() (or " + hint + ")"))


def _array_info(arr: zarr.Array, *, load: bool) -> _Info:
    dims = arr.metadata.dimension_names if hasattr(arr.metadata, "dimension_names") else None
    return _Info(
        shape=tuple(int(s) for s in arr.shape),
        dtype=str(arr.dtype),
        chunks=tuple(int(c) for c in arr.chunks),
        dims=tuple(dims) if dims is not None else None,
        load=(lambda a=arr: a[...]) if load else None,
    )


_BIG = ("raw", "dark_frames", "truth/btf", "truth/btf_2x")


def _validate_group(
    group: zarr.Group, *, require_complete: bool, check_flag: bool = True,
) -> list[Problem]:
    problems: list[Problem] = []
    attrs = dict(group.attrs)
    other = attrs.get("schema")
    if isinstance(other, str) and other != SCHEMA_NAME:
        # another kind of store (e.g. a btf-texture store): one problem, not a list of everything missing
        return [Problem("attrs", "schema", repr(SCHEMA_NAME), repr(other),
                        "this is not a capture store; give the capture store (btf simulate / btf import-raw output)")]
    _check_attrs(attrs, problems)

    members = dict(group.members(max_depth=None))
    infos: dict[str, _Info] = {}
    for name in _ARRAYS:
        node = members.get(name)
        if node is None:
            problems.append(Problem(
                name, None, f"array {name!r}", "nothing",
                "the store is incomplete or was not written by create_capture_store; "
                "recreate it (--overwrite; overwrite=True from Python)"))
        elif not isinstance(node, zarr.Array):
            problems.append(Problem(name, None, "an array", "a group", "recreate the store"))
        else:
            infos[name] = _array_info(node, load=name not in _BIG)
    truth = members.get("truth")
    if truth is not None:
        if not isinstance(truth, zarr.Group):
            problems.append(Problem("truth", None, "a group", "an array", "recreate the store"))
        else:
            for name in _TRUTH_ARRAYS:
                node = members.get(name)
                if node is None:
                    problems.append(Problem(
                        name, None, f"array {name!r} (the truth group exists)", "nothing",
                        "re-run the simulator to rewrite the ground truth"))
                elif not isinstance(node, zarr.Array):
                    problems.append(Problem(name, None, "an array", "a group", "recreate the store"))
                else:
                    infos[name] = _array_info(node, load=name not in _BIG)
            try:
                json.dumps(dict(truth.attrs), allow_nan=False)
            except (TypeError, ValueError) as e:
                problems.append(Problem("truth", "attrs", "plain JSON attributes", str(e),
                                        "rewrite the material attrs as plain JSON"))

    planned = None
    plan = members.get("plan")
    if plan is not None:
        shot = members.get("plan/shot")
        if not isinstance(shot, zarr.Array) or shot.ndim != 3:
            problems.append(Problem("plan/shot", None, "an int32 array (n_turn, n_cam, n_illum)",
                                    "nothing" if shot is None else f"shape {getattr(shot, 'shape', None)}",
                                    "re-run `btf simulate --plan` (the plan group is incomplete)"))
        else:
            planned = np.asarray(shot[...]) >= 0
            raw = infos.get("raw")
            if raw is not None and len(raw.shape) == 6 and planned.shape != tuple(raw.shape[:3]):
                problems.append(Problem("plan/shot", None, f"shape {tuple(raw.shape[:3])} (n_turn, n_cam, n_illum)",
                                        f"shape {planned.shape}", "re-run `btf simulate --plan`"))
                planned = None
    sizes = _Sizes()
    ts = attrs.get("texture_shape")
    if isinstance(ts, list) and len(ts) == 2 and all(isinstance(x, int) and x > 0 for x in ts):
        sizes.seed("tex_row", ts[0], "attrs['texture_shape'][0]")
        sizes.seed("tex_col", ts[1], "attrs['texture_shape'][1]")
        sizes.seed("tex2_row", 2 * ts[0], "2 * attrs['texture_shape'][0]")
        sizes.seed("tex2_col", 2 * ts[1], "2 * attrs['texture_shape'][1]")
    usable = _check_shapes(infos, sizes, problems)
    data = _check_content(infos, usable, sizes, attrs, problems, planned=planned)
    _check_chunk_files(group, data, attrs, problems)
    _check_completeness(data, attrs, sizes, problems,
                        require_complete=require_complete, check_flag=check_flag, planned=planned)
    return problems


#: Frame arrays whose chunks a resume marker says were written: ``array -> (marker, marker axes)``. Dark
#: frames are not listed: all-zero dark frames are accepted input (below the black level), and Zarr does
#: not store an all-zero chunk.
_MARKED = {"raw": ("written", "(t, c, i)")}


def _check_chunk_files(group: zarr.Group, data: Mapping[str, np.ndarray], attrs: Mapping[str, Any],
                       problems: list[Problem]) -> None:
    """A frame chunk whose marker says written must have its file: Zarr reads a missing chunk as zeros,
    which ingest would take for an unusable bracket. One ``stat`` per written bracket (local stores only;
    ``btf validate --deep`` lists the chunks of any store). With ``black_level`` 0 an all-zero bracket is
    possible and Zarr does not store it, so nothing is checked then (above a black level of 0 no sensor
    gives an all-zero bracket)."""
    black = attrs.get("black_level")
    if not isinstance(black, (int, float)) or black <= 0 or getattr(group.store, "root", None) is None:
        return
    for name, (marker_name, axes) in _MARKED.items():
        marker, arr = data.get(marker_name), group.get(name)
        if marker is None or not isinstance(arr, zarr.Array) or tuple(arr.cdata_shape[:marker.ndim]) != marker.shape:
            continue
        written = np.argwhere(marker == 1)
        chunks = [tuple(int(i) for i in w) + (0,) * (arr.ndim - marker.ndim) for w in written]
        missing = [c for c, ok in zip(chunks, chunk_files_exist(arr, chunks)) if not ok]
        if missing:
            problems.append(Problem(
                name, f"chunk {_listing(np.array(missing))}",
                f"a chunk file for each bracket that {marker_name}{axes} = 1 marks as written",
                f"chunk file missing for {len(missing)} chunk(s) (Zarr would read them as zeros)",
                "the store was damaged after writing; write the capture again (`btf simulate --overwrite` / "
                "`btf import-raw --overwrite`) or restore it from a backup"))


def _is_url(path: Any) -> bool:
    return isinstance(path, str) and "://" in path


def validate_capture_store(path: str | os.PathLike, *, require_complete: bool = True) -> list[Problem]:
    """Check a capture store against the schema and list every problem.

    Reads the attributes and the small arrays (never the frames).

    Parameters
    ----------
    path : str or path-like
        Store directory or fsspec URL.
    require_complete : bool
        Report brackets (dark frames, ground truth) not yet written and an
        unset ``complete`` flag as problems.

    Returns
    -------
    list of Problem
        Empty when the store is valid. A missing or unreadable store gives a
        single problem. Content problems never raise.
    """
    if not _is_url(path) and not os.path.exists(os.fspath(path)):
        return [Problem(_STORE, None, "a capture store directory", f"nothing at {os.fspath(path)!r}",
                        "check the path, or create the store (`btf simulate` / `btf ingest`)")]
    try:
        group = zarr.open_group(_store_arg(path), mode="r", zarr_format=3)
    except Exception as e:  # noqa: BLE001 - any failure to open is one problem
        return [Problem(_STORE, None, "a Zarr v3 group (zarr.json with node_type 'group')",
                        f"{type(e).__name__}: {e}",
                        "this is not a capture store; check the path")]
    return _validate_group(group, require_complete=require_complete)


def _store_arg(path: Any) -> Any:
    return path if _is_url(path) else os.fspath(path)


# --------------------------------------------------------------------------
# Metadata -> store
# --------------------------------------------------------------------------


def _meta_attrs(meta: CaptureMetadata) -> dict[str, Any]:
    """Root attributes for ``meta`` as plain JSON (raises on NaN / non-JSON)."""
    prov = dict(meta.provenance or {})
    prov.setdefault("code_version", btfcore.__version__)
    prov.setdefault("seed", None)
    prov.setdefault("created", _dt.datetime.now(_dt.timezone.utc).isoformat())
    attrs = {
        "schema": SCHEMA_NAME,
        "schema_version": SCHEMA_VERSION,
        "device": meta.device,
        "bayer_pattern": meta.bayer_pattern,
        "black_level": meta.black_level,
        "white_level": meta.white_level,
        "bit_depth": meta.bit_depth,
        "sensor": {k: (meta.sensor or {}).get(k) for k in SENSOR_KEYS}
        | {k: v for k, v in (meta.sensor or {}).items() if k not in SENSOR_KEYS},
        "sample_size_m": meta.sample_size_m,
        "texture_shape": list(meta.texture_shape) if meta.texture_shape is not None else None,
        "lv_order": list(LV_ORDER),
        "units": dict(UNITS),
        "provenance": prov,
        "complete": False,
    }
    return to_json_attr(attrs)


def _meta_problems(meta: CaptureMetadata) -> tuple[list[Problem], dict[str, Any] | None, dict[str, np.ndarray]]:
    """Validate in-memory metadata with the same rules as a stored one."""
    problems: list[Problem] = []
    try:
        attrs = _meta_attrs(meta)
    except (TypeError, ValueError) as e:
        return [Problem(_ATTRS, None, "plain-JSON metadata without NaN/Inf", str(e),
                        "convert the value (unknowns are null)")], None, {}
    _check_attrs(attrs, problems, in_memory=True)
    arrays: dict[str, np.ndarray] = {}
    infos: dict[str, _Info] = {}
    for name in _META_ARRAY_FIELDS:
        dtype = _ARRAYS[name][0]
        try:
            a = np.asarray(getattr(meta, name))
            if a.dtype.kind not in "biuf":
                raise TypeError(f"dtype {a.dtype}")
            arrays[name] = a.astype(np.float64)  # checks run on exact values
        except (TypeError, ValueError) as e:
            problems.append(Problem(name, None, f"a numeric array castable to {dtype}",
                                    str(e), f"pass {name} as a numpy array"))
            continue
        infos[name] = _Info(a.shape, dtype, None, None, (lambda v=arrays[name]: v))
    sizes = _Sizes()
    n_exp, roi = meta.n_exp, meta.roi_shape
    if not (isinstance(n_exp, (int, np.integer)) and not isinstance(n_exp, bool) and n_exp >= 1):
        problems.append(Problem("raw", "n_exp", "an integer >= 1", repr(n_exp),
                                "set the number of exposures per bracket"))
    else:
        sizes.seed("exposure", int(n_exp), "meta.n_exp")
    if not (isinstance(roi, (tuple, list, np.ndarray)) and len(roi) == 2
            and all(isinstance(x, (int, np.integer)) and x > 0 for x in roi)):
        problems.append(Problem("raw", "roi_shape", "(rows, cols), positive integers", repr(roi),
                                "set the raw frame (ROI) size"))
    else:
        sizes.seed("row", int(roi[0]), "meta.roi_shape[0]")
        sizes.seed("col", int(roi[1]), "meta.roi_shape[1]")
    usable = _check_shapes(infos, sizes, problems, check_layout=False)
    planned = None
    if meta.plan_shot is not None or meta.plan is not None:
        shot = np.asarray(meta.plan_shot) if meta.plan_shot is not None else None
        want = (meta.n_turn, meta.n_cam, meta.n_illum)
        if shot is None or meta.plan is None:
            problems.append(Problem("plan", None, "plan and plan_shot together", "only one of them",
                                    "pass both (tasks.measurement.plan_layout)"))
        elif shot.shape != want or shot.dtype.kind not in "iu" or (shot.size and shot.min() < -1):
            problems.append(Problem("plan/shot", None, f"integers >= -1 of shape {want}",
                                    f"{shot.dtype} {shot.shape}", "build it with tasks.measurement.plan_layout"))
        else:
            planned = shot >= 0
            try:
                json.dumps(meta.plan, allow_nan=False)
            except (TypeError, ValueError) as e:
                problems.append(Problem("plan", None, "plain JSON (CapturePlan.to_dict())", str(e),
                                        "pass plan.to_dict()"))
    _check_content(infos, usable, sizes, attrs, problems, planned=planned)
    return problems, attrs, arrays


def create_capture_store(
    path: str | os.PathLike,
    meta: CaptureMetadata,
    *,
    with_truth: bool = False,
    overwrite: bool = False,
) -> CaptureStore:
    """Create a capture store, or reopen an unfinished one to resume.

    All arrays are created; ``raw`` and the other per-view arrays are filled
    lazily (fill value 0, nothing written to disk until a writer owns a
    chunk). The metadata arrays and root attributes are written and
    ``complete`` is false.

    Parameters
    ----------
    path : str or path-like
        Store directory or fsspec URL.
    meta : CaptureMetadata
        Validated before anything is written.
    with_truth : bool
        Create the ``truth/`` group (simulator only).
    overwrite : bool
        Delete whatever is at ``path`` first.

    Returns
    -------
    CaptureStore
        Opened with mode ``"r+"``.

    Raises
    ------
    CaptureStoreError
        If ``meta`` violates the schema (listing every problem).
    FileExistsError
        If ``path`` holds a complete store, a store of another config
        (``provenance.config_hash``) or something that is not a capture store,
        and ``overwrite`` is false.

    Notes
    -----
    An incomplete store at ``path`` with the same ``config_hash`` and the
    same metadata is reopened as is: finished views are kept and
    :meth:`CaptureStore.pending_views` lists the rest.
    """
    problems, attrs, arrays = _meta_problems(meta)
    if problems:
        raise CaptureStoreError(path, problems)
    assert attrs is not None
    if not overwrite:
        existing = _existing_store(path, meta, attrs, with_truth)
        if existing is not None:
            return existing
    group = begin_store(path)
    _create_arrays(group, meta, arrays, with_truth)
    if meta.plan_shot is not None:
        shot = np.asarray(meta.plan_shot, dtype=np.int32)
        pg = group.create_group("plan")
        create_array(pg, "shot", shape=shot.shape, dtype="int32", chunks=shot.shape, fill_value=-1,
                        dimension_names=["turntable", "camera", "illumination"], compressors=None)[...] = shot
        pg.attrs.put(to_json_attr({"plan": meta.plan}))
    group.attrs.put(attrs)
    return CaptureStore(path, "r+", group=finish_store(path, group))


def check_capture_target(path: str | os.PathLike, meta: CaptureMetadata, *, with_truth: bool = False) -> None:
    """Raise what :func:`create_capture_store` (without ``overwrite``) would refuse at ``path``, writing nothing.

    Raises
    ------
    CaptureStoreError
        ``meta`` violates the schema.
    FileExistsError
        ``path`` holds a complete store, one of another config, or something else.
    """
    problems, attrs, _ = _meta_problems(meta)
    if problems:
        raise CaptureStoreError(path, problems)
    _existing_store(path, meta, attrs, with_truth)


def _existing_store(path, meta: CaptureMetadata, attrs: dict, with_truth: bool) -> CaptureStore | None:
    if _is_url(path):
        try:
            group = zarr.open_group(path, mode="r", zarr_format=3)
        except (FileNotFoundError, zarr.errors.NodeNotFoundError):
            return None
        old = dict(group.attrs)
    else:
        p = os.fspath(path)
        if not os.path.exists(p):
            return None
        if os.path.isdir(p) and not os.listdir(p):
            return None
        if not os.path.isfile(os.path.join(p, "zarr.json")):
            raise FileExistsError(
                f"{p!r} exists and is not a capture store; choose another path or pass "
                "--overwrite (overwrite=True) to delete it")
        try:
            found = zarr.open_group(p, mode="r", zarr_format=3)
            old = dict(found.attrs)
        except Exception as e:  # noqa: BLE001
            raise FileExistsError(
                f"{p!r} exists and is not a readable Zarr v3 group ({e}); choose another path "
                "or pass --overwrite (overwrite=True) to delete it") from e
        if not old and set(found.keys()) <= {*_ARRAYS, "truth", "plan"}:
            # a skeleton whose creation was killed before its attributes (stores made before
            # tasks.staging.begin_store): nothing was captured into it yet, so it is built again
            return None
    if old.get("schema") != SCHEMA_NAME:
        raise FileExistsError(
            f"{path!s} holds a store of schema {old.get('schema')!r}, not {SCHEMA_NAME!r}; "
            "choose another path or pass --overwrite (overwrite=True) to delete it")
    if old.get("complete") is True:
        raise FileExistsError(
            f"{path!s} already holds a complete capture store; pass --overwrite (overwrite=True) to replace "
            "it or choose another path")
    old_hash = (old.get("provenance") or {}).get("config_hash")
    new_hash = attrs["provenance"]["config_hash"]
    if old_hash != new_hash:
        raise FileExistsError(
            f"{path!s} holds an unfinished capture store of another configuration "
            f"(config_hash {old_hash!r}, this run has {new_hash!r}); it cannot be resumed with "
            "this config. Re-run with the original config to finish it, pass --overwrite (overwrite=True) "
            "to start over, or choose another path")
    store = open_capture_store(path, "r+", require_complete=False)
    diff = _meta_differences(store.meta, meta)
    if diff:
        raise FileExistsError(
            f"{path!s} holds an unfinished store with the same config_hash {new_hash!r} but "
            f"different metadata ({'; '.join(diff)}); the config hash does not cover everything "
            "that changed. Pass --overwrite (overwrite=True) to start over or choose another path")
    if with_truth != store.has_truth:
        raise FileExistsError(
            f"{path!s} holds an unfinished store {'with' if store.has_truth else 'without'} "
            f"ground truth but with_truth={with_truth}; pass --overwrite (overwrite=True) to start over")
    return store


def _meta_differences(a: CaptureMetadata, b: CaptureMetadata) -> list[str]:
    out = []
    for f in _META_ATTR_FIELDS:
        va, vb = to_json_attr(getattr(a, f)), to_json_attr(getattr(b, f))
        if f == "sensor":
            va = {k: va.get(k) for k in SENSOR_KEYS}
            vb = {k: (vb or {}).get(k) for k in SENSOR_KEYS}
        if va != vb:
            out.append(f"{f}: {va!r} != {vb!r}")
    for f in _META_ARRAY_FIELDS:
        va, vb = np.asarray(getattr(a, f), dtype=float), np.asarray(getattr(b, f), dtype=float)
        if va.shape != vb.shape or not np.array_equal(va, vb):
            out.append(f"{f} differs")
    if int(a.n_exp) != int(b.n_exp):
        out.append(f"n_exp: {a.n_exp} != {b.n_exp}")
    sa, sb = a.plan_shot, b.plan_shot
    if (sa is None) != (sb is None) or (sa is not None and not np.array_equal(sa, sb)):
        out.append("plan/shot differs")
    if tuple(map(int, a.roi_shape)) != tuple(map(int, b.roi_shape)):
        out.append(f"roi_shape: {tuple(a.roi_shape)} != {tuple(b.roi_shape)}")
    return out


def _create_arrays(group: zarr.Group, meta: CaptureMetadata, arrays: Mapping[str, np.ndarray],
                   with_truth: bool) -> None:
    n_turn, n_cam, n_illum, n_exp, rows, cols = meta.raw_shape
    sizes = {
        "turntable": n_turn, "camera": n_cam, "illumination": n_illum, "exposure": n_exp,
        "row": rows, "col": cols, "led": meta.n_leds, "dark": meta.n_dark,
        "lv": meta.n_lv, **_FIXED_SIZES,
    }
    if with_truth:
        h, w = map(int, meta.texture_shape)
        sizes.update(tex_row=h, tex_col=w, tex2_row=2 * h, tex2_col=2 * w)

    def make(g: zarr.Group, name: str, spec, data: np.ndarray | None = None):
        dtype, axes, rule = spec
        shape = tuple(sizes[k] for _, k in axes)
        arr = create_array(g,
            name.split("/")[-1], shape=shape, dtype=dtype,
            chunks=_expected_chunks(rule, shape, sizes), fill_value=0,
            dimension_names=[d for d, _ in axes], compressors=None,
        )
        if data is not None and data.size:
            arr[...] = data.astype(dtype)
        return arr

    for name, spec in _ARRAYS.items():
        make(group, name, spec, arrays.get(name))
    if with_truth:
        tg = group.create_group("truth")
        for name, spec in _TRUTH_ARRAYS.items():
            make(tg, name, spec)


# --------------------------------------------------------------------------
# Writing whole chunks
# --------------------------------------------------------------------------


def _normalise_selection(array: zarr.Array, selection: Any) -> tuple[tuple[slice, ...], tuple[int, ...]]:
    if not isinstance(selection, tuple):
        selection = (selection,)
    if any(s is Ellipsis for s in selection):
        k = selection.index(Ellipsis)
        fill = array.ndim - (len(selection) - 1)
        selection = selection[:k] + (slice(None),) * fill + selection[k + 1:]
    if len(selection) > array.ndim:
        raise ValueError(f"selection {selection!r} has more entries than {array.ndim} dimensions")
    selection = selection + (slice(None),) * (array.ndim - len(selection))
    out, dropped = [], []
    for ax, (s, n) in enumerate(zip(selection, array.shape)):
        if isinstance(s, (int, np.integer)):
            i = int(s) + (n if s < 0 else 0)
            if not 0 <= i < n:
                raise IndexError(f"index {s} out of range for axis {ax} of length {n}")
            out.append(slice(i, i + 1))
            dropped.append(ax)
        elif isinstance(s, slice):
            start, stop, step = s.indices(n)
            if step != 1:
                raise ValueError(f"axis {ax}: step {step} is not a contiguous block")
            out.append(slice(start, stop))
        else:
            raise ValueError(f"axis {ax}: only ints and contiguous slices are chunk-aligned, got {s!r}")
    return tuple(out), tuple(dropped)


def write_chunk_aligned(array: zarr.Array, selection: Any, data: np.ndarray) -> None:
    """Write ``data`` into ``array[selection]`` only if it covers whole chunks.

    Parallel writers that share a chunk silently lose data (each rewrites the
    whole chunk from what it read), so every write must cover whole chunks
    (DESIGN §5).

    Parameters
    ----------
    array : zarr.Array
        Target array (not sharded).
    selection : int, slice, Ellipsis or tuple of those
        A block: ints and slices with step 1.
    data : ndarray
        Values, broadcastable to the selection.

    Raises
    ------
    ValueError
        If a block edge does not fall on a chunk boundary (or the array end),
        naming the axis, the edges and the chunk length.
    """
    sel, dropped = _normalise_selection(array, selection)
    for ax, (s, c, n) in enumerate(zip(sel, array.chunks, array.shape)):
        if s.start % c or (s.stop % c and s.stop != n) or s.stop <= s.start:
            raise ValueError(
                f"write to {array.path or array.name}{list(zip([x.start for x in sel], [x.stop for x in sel]))} "
                f"is not chunk-aligned on axis {ax}: [{s.start}, {s.stop}) with chunk length {c} "
                f"(array length {n}); writers must own whole chunks, so write the whole block "
                f"[{s.start // c * c}, {min(n, -(-s.stop // c) * c)})")
    full = tuple(s.stop - s.start for s in sel)
    natural = tuple(n for ax, n in enumerate(full) if ax not in dropped)
    data = np.asarray(data)
    if data.shape != full:
        try:
            data = np.broadcast_to(data, natural).reshape(full)
        except ValueError as e:
            raise ValueError(
                f"data of shape {data.shape} does not fit the block of shape {natural}") from e
    array[sel] = data


# --------------------------------------------------------------------------
# The store
# --------------------------------------------------------------------------


def open_capture_store(
    path: str | os.PathLike, mode: str = "r", *, require_complete: bool = True,
) -> CaptureStore:
    """Open and validate a capture store.

    Parameters
    ----------
    path : str or path-like
        Store directory or fsspec URL.
    mode : {"r", "r+"}
        Read-only, or read/write for resuming writers.
    require_complete : bool
        Also refuse a store whose brackets are not all written / that was never
        marked complete.

    Returns
    -------
    CaptureStore

    Raises
    ------
    CaptureStoreError
        Listing every problem at once.
    """
    if mode not in ("r", "r+"):
        raise ValueError(f"mode must be 'r' or 'r+', got {mode!r}; create stores with create_capture_store")
    problems = validate_capture_store(path, require_complete=require_complete)
    if problems:
        raise CaptureStoreError(path, problems)
    return CaptureStore(path, mode)


class CaptureStore:
    """An opened capture store.

    Use :func:`open_capture_store` or :func:`create_capture_store` rather than
    the constructor, which does not validate.

    Attributes
    ----------
    path : str
        Store path or URL.
    group : zarr.Group
        The root group.
    meta : CaptureMetadata
        Metadata rebuilt from the store.
    raw : zarr.Array
        ``(n_turn, n_cam, n_illum, n_exp, rows, cols)`` uint16 frames.
    dark_frames : zarr.Array
        ``(n_cam, n_dark, rows, cols)`` uint16.
    """

    def __init__(self, path: str | os.PathLike, mode: str = "r", *, group: zarr.Group | None = None) -> None:
        self.path = str(path) if _is_url(path) else os.fspath(path)
        self.mode = mode
        self.group = group if group is not None else zarr.open_group(
            _store_arg(path), mode=mode, zarr_format=3)
        self.raw: zarr.Array = self.group["raw"]
        self.dark_frames: zarr.Array = self.group["dark_frames"]
        self.meta = self._read_meta()

    def __repr__(self) -> str:
        return (f"CaptureStore({self.path!r}, mode={self.mode!r}, raw={self.raw.shape}, "
                f"complete={self.complete}, pending={len(self.pending_views())} view(s))")

    def _read_meta(self) -> CaptureMetadata:
        a = dict(self.group.attrs)
        arr = {n: self.group[n][...] for n in _META_ARRAY_FIELDS}
        return CaptureMetadata(
            device=a.get("device"), bayer_pattern=a.get("bayer_pattern"),
            black_level=a.get("black_level"), white_level=a.get("white_level"),
            bit_depth=a.get("bit_depth"), sensor=dict(a.get("sensor") or {}),
            sample_size_m=a.get("sample_size_m"),
            texture_shape=tuple(a.get("texture_shape") or ()),
            n_exp=int(self.raw.shape[3]), roi_shape=(int(self.raw.shape[4]), int(self.raw.shape[5])),
            provenance=dict(a.get("provenance") or {}), **arr, **self._read_plan(),
        )

    def _read_plan(self) -> dict[str, Any]:
        try:
            plan = self.group["plan"]
        except KeyError:
            return {}
        return {"plan": plan.attrs.get("plan"), "plan_shot": np.asarray(plan["shot"][...])}

    @property
    def is_plan_capture(self) -> bool:
        """Whether the capture executed an acquisition plan (it has a ``plan`` group)."""
        return self.meta.plan_shot is not None

    @property
    def planned(self) -> np.ndarray:
        """``(n_turn, n_cam, n_illum)`` bool: the brackets the capture takes (all without a plan)."""
        if self.meta.plan_shot is None:
            return np.ones((self.n_turn, self.n_cam, self.n_illum), dtype=bool)
        return self.meta.plan_shot >= 0

    # ---- shapes ------------------------------------------------------------
    @property
    def n_turn(self) -> int:
        return int(self.raw.shape[0])

    @property
    def n_cam(self) -> int:
        return int(self.raw.shape[1])

    @property
    def n_illum(self) -> int:
        return int(self.raw.shape[2])

    @property
    def n_exp(self) -> int:
        return int(self.raw.shape[3])

    @property
    def roi_shape(self) -> tuple[int, int]:
        return int(self.raw.shape[4]), int(self.raw.shape[5])

    @property
    def n_leds(self) -> int:
        return int(self.group["led_position"].shape[0])

    @property
    def n_dark(self) -> int:
        return int(self.group["dark_exposure_time"].shape[0])

    @property
    def n_lv(self) -> int:
        return self.n_turn * self.n_cam * self.n_leds

    @property
    def texture_shape(self) -> tuple[int, int]:
        h, w = self.meta.texture_shape
        return int(h), int(w)

    # ---- small arrays (read fresh) -------------------------------------
    @property
    def exposure_time(self) -> np.ndarray:
        """``(n_turn, n_cam, n_illum, n_exp)`` float64 seconds (0 where not written)."""
        return self.group["exposure_time"][...]

    @property
    def written(self) -> np.ndarray:
        """``(n_turn, n_cam, n_illum)`` uint8 resume markers."""
        return self.group["written"][...]

    @property
    def illumination(self) -> np.ndarray:
        return self.meta.illumination

    @property
    def led_position(self) -> np.ndarray:
        return self.meta.led_position

    @property
    def camera_K(self) -> np.ndarray:
        return self.meta.camera_K

    @property
    def camera_R(self) -> np.ndarray:
        return self.meta.camera_R

    @property
    def camera_t(self) -> np.ndarray:
        return self.meta.camera_t

    @property
    def turntable_angle(self) -> np.ndarray:
        return self.meta.turntable_angle

    @property
    def homography(self) -> np.ndarray:
        return self.meta.homography

    @property
    def dark_exposure_time(self) -> np.ndarray:
        return self.meta.dark_exposure_time

    @property
    def attrs(self) -> dict:
        return dict(self.group.attrs)

    @property
    def complete(self) -> bool:
        return self.group.attrs.get("complete") is True

    @property
    def has_truth(self) -> bool:
        return "truth" in self.group

    @property
    def truth(self) -> zarr.Group:
        if not self.has_truth:
            raise KeyError(f"{self.path} has no ground truth (created with with_truth=False)")
        return self.group["truth"]

    # ---- reading -------------------------------------------------------------
    def read_bracket(self, t: int, c: int, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Read one exposure bracket.

        Parameters
        ----------
        t, c, i : int
            Turntable, camera and illumination index.

        Returns
        -------
        frames : (n_exp, rows, cols) ndarray of uint16
        exposure_time : (n_exp,) ndarray of float64
            Seconds, increasing.

        Raises
        ------
        CorruptChunkError
            The bracket's chunk fails its checksum or is truncated, or its file is missing although
            ``written[t, c, i]`` marks it written (naming the store, array and chunk).
        """
        if int(self.group["written"][t, c, i]) == 1 and float(self.meta.black_level or 0) > 0:
            chunk = (int(t), int(c), int(i), 0, 0, 0)
            if not chunk_files_exist(self.raw, [chunk])[0]:
                raise missing_problem(self.path, "raw", chunk, "written", chunk[:3],
                                      rerun_hint(self.attrs)).error()
        return self.raw[t, c, i], self.group["exposure_time"][t, c, i]

    def read_raw(self, t: int, c: int, window: tuple[slice, slice], illuminations: Sequence[int] | None = None,
                 out: np.ndarray | None = None) -> np.ndarray:
        """Read a window of the raw brackets of view ``(t, c)``.

        Parameters
        ----------
        t, c : int
            Turntable and camera index.
        window : (slice, slice)
            Rows and columns of the region of interest.
        illuminations : sequence of int, optional
            Illumination indices to read (all when omitted, one read into ``out``).
        out : (n_illum, n_exp, rows, cols) ndarray of uint16, optional
            Buffer to read all illuminations into (reused across views by the ingest).

        Returns
        -------
        (n, n_exp, rows, cols) ndarray of uint16

        Raises
        ------
        CorruptChunkError
            A chunk fails its checksum, is truncated or is missing (naming the store, array and chunk).
        ValueError
            A chunk of a store without checksums does not decode to its shape.
        """
        try:
            if illuminations is None:
                selection = (t, c, slice(None), slice(None), window[0], window[1])
                if out is None:
                    return self.raw.get_basic_selection(selection)
                self.raw.get_basic_selection(selection, out=default_buffer_prototype().nd_buffer.from_numpy_array(out))
                return out
            return np.stack([self.raw[t, c, int(i), :, window[0], window[1]] for i in illuminations])
        except (OSError, MemoryError, CorruptChunkError):
            raise                                   # the machine (worth a retry), or already named
        except Exception as exc:  # noqa: BLE001 - a chunk that does not decode to its shape
            raise ValueError(
                f"{self.path}: raw[(t, c)=({t}, {c})] cannot be read ({type(exc).__name__}: {exc}): a chunk file "
                "is corrupt or truncated, so the store is damaged; write the capture again "
                "(btf simulate / btf import-raw)") from exc

    def pending_views(self) -> list[tuple[int, int]]:
        """Views ``(t, c)`` with any bracket not written (or, with truth, no truth yet).

        Returns
        -------
        list of (int, int)
            Row-major order.
        """
        todo = ((self.written != 1) & self.planned).any(axis=2)
        if self.has_truth:
            todo |= self.truth["written"][...] != 1
        return [(int(t), int(c)) for t, c in np.argwhere(todo)]

    # ---- writing -------------------------------------------------------------
    def _writable(self) -> None:
        if self.mode == "r":
            raise PermissionError(
                f"{self.path} is open read-only; use open_capture_store(path, 'r+', "
                "require_complete=False) to write")

    def _view_index(self, t: int, c: int) -> tuple[int, int]:
        if not (0 <= t < self.n_turn and 0 <= c < self.n_cam):
            raise IndexError(f"view (t, c)=({t}, {c}) outside ({self.n_turn}, {self.n_cam}) views")
        return int(t), int(c)

    def _check_frames(self, frames: Any, shape: tuple[int, ...], what: str) -> np.ndarray:
        frames = np.asarray(frames)
        if frames.shape != shape:
            raise ValueError(f"{what}: expected shape {shape}, got {frames.shape}")
        if frames.dtype.kind not in "ui":
            raise ValueError(
                f"{what}: expected integer raw DN (uint16), got {frames.dtype}; do not pass "
                "linearised or float frames as raw")
        bd = int(self.meta.bit_depth)
        if frames.size and (frames.min() < 0 or frames.max() > 2**bd - 1):
            raise ValueError(
                f"{what}: values in [{frames.min()}, {frames.max()}] outside the {bd}-bit range "
                f"[0, {2**bd - 1}]; check bit_depth / the raw decoder's bit shift")
        return frames.astype(np.uint16, copy=False)

    def write_bracket(self, t: int, c: int, frames: np.ndarray, exposure_time: np.ndarray) -> None:
        """Write every illumination's exposure bracket of view ``(t, c)``.

        The view owns whole chunks of ``raw`` (one per illumination),
        ``exposure_time`` and ``written``. The data go first and the marker
        ``written[t, c, :] = 1`` last, so a killed write is redone on resume.
        Writing a view twice is harmless (idempotent).

        Parameters
        ----------
        t, c : int
            Turntable and camera index.
        frames : (n_illum, n_exp, rows, cols) ndarray of uint16
            Raw Bayer frames in DN. In a plan capture only the view's planned
            illuminations (``planned[t, c]``), in order.
        exposure_time : (n_illum, n_exp) ndarray of float
            Seconds, > 0, strictly increasing along the exposure axis (a plan
            capture: the same rows as ``frames``; a shorter bracket ends in 0 s).

        Raises
        ------
        ValueError
            Wrong shape or dtype, values beyond the bit depth, or bad exposure
            times (naming ``(t, c, i)``).
        """
        self._writable()
        t, c = self._view_index(t, c)
        plan = self.meta.plan_shot is not None
        idx = np.flatnonzero(self.planned[t, c])
        shape = (len(idx) if plan else self.n_illum, self.n_exp, *self.roi_shape)
        frames = self._check_frames(frames, shape, f"frames of view (t, c)=({t}, {c})"
                                    + (" (its planned illuminations)" if plan else ""))
        et = np.asarray(exposure_time, dtype=np.float64)
        if et.shape != shape[:2]:
            raise ValueError(f"exposure_time of view ({t}, {c}): expected shape {shape[:2]}, got {et.shape}")
        check = trailing_steps_filled(et) if plan else et
        for k in range(len(et)):
            e, i = check[k], int(idx[k]) if plan else k
            if not (np.isfinite(e).all() and (e > 0).all() and (np.diff(e) > 0).all()):
                raise ValueError(
                    f"exposure_time[(t, c, i)=({t}, {c}, {i})] = {et[k].tolist()}: exposure times must "
                    "be finite, > 0 s and strictly increasing" + (" (then 0 for steps not taken)" if plan else "")
                    + "; check the manifest / EXIF for this bracket")
        if not plan:
            write_chunk_aligned(self.raw, (t, c), frames)
            write_chunk_aligned(self.group["exposure_time"], (t, c), et)
            write_chunk_aligned(self.group["written"], (t, c), np.ones(self.n_illum, np.uint8))
            return
        full_et = np.zeros((self.n_illum, self.n_exp))
        full_et[idx] = et
        for k, i in enumerate(idx.tolist()):
            write_chunk_aligned(self.raw, (t, c, i), frames[k])        # one chunk per illumination
        write_chunk_aligned(self.group["exposure_time"], (t, c), full_et)
        write_chunk_aligned(self.group["written"], (t, c), self.planned[t, c].astype(np.uint8))

    def write_dark_frames(self, frames: np.ndarray, *, camera: int | None = None) -> None:
        """Write dark frames (all cameras, or one camera's chunk).

        Parameters
        ----------
        frames : (n_cam, n_dark, rows, cols) or (n_dark, rows, cols) ndarray of uint16
            The latter with ``camera`` given.
        camera : int, optional
            Write only this camera's chunk.
        """
        self._writable()
        rows, cols = self.roi_shape
        if camera is None:
            frames = self._check_frames(frames, (self.n_cam, self.n_dark, rows, cols), "dark frames")
            write_chunk_aligned(self.dark_frames, (slice(None),), frames)
            write_chunk_aligned(self.group["dark_written"], (slice(None),), np.ones(self.n_cam, np.uint8))
        else:
            if not 0 <= camera < self.n_cam:
                raise IndexError(f"camera {camera} outside {self.n_cam} cameras")
            frames = self._check_frames(frames, (self.n_dark, rows, cols), f"dark frames of camera {camera}")
            write_chunk_aligned(self.dark_frames, (camera,), frames)
            write_chunk_aligned(self.group["dark_written"], (camera,), np.ones(1, np.uint8))

    def write_truth_view(self, t: int, c: int, btf: np.ndarray, btf_2x: np.ndarray) -> None:
        """Write the ground-truth BTF rows of view ``(t, c)`` (one chunk each).

        Parameters
        ----------
        t, c : int
            Turntable and camera index.
        btf : (n_leds, h, w, 3) ndarray of float
            Texture-resolution radiance, rows ``lv = (t * n_cam + c) * n_leds + led``.
        btf_2x : (n_leds, 2h, 2w, 3) ndarray of float
            Twice the resolution.
        """
        self._writable()
        truth = self.truth
        t, c = self._view_index(t, c)
        h, w = self.texture_shape
        n = self.n_leds
        for name, a, shp in (("btf", btf, (n, h, w, 3)), ("btf_2x", btf_2x, (n, 2 * h, 2 * w, 3))):
            a = np.asarray(a)
            if a.shape != shp:
                raise ValueError(f"truth {name} of view ({t}, {c}): expected shape {shp}, got {a.shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"truth {name} of view ({t}, {c}) holds NaN/Inf; fix the simulator output")
        lv0 = (t * self.n_cam + c) * n
        write_chunk_aligned(truth["btf"], slice(lv0, lv0 + n), np.asarray(btf, np.float32))
        write_chunk_aligned(truth["btf_2x"], slice(lv0, lv0 + n), np.asarray(btf_2x, np.float32))
        write_chunk_aligned(truth["written"], (t, c), np.ones((), np.uint8))

    def write_truth_directions(self, light_dir: np.ndarray, view_dir: np.ndarray, lv_index: np.ndarray) -> None:
        """Write the ground-truth light / view directions of every pair.

        Parameters
        ----------
        light_dir, view_dir : (n_lv, 3) ndarray of float
            Unit vectors in the sample frame.
        lv_index : (n_lv, 3) ndarray of int
            ``(turntable, camera, led)`` of each row, row-major.
        """
        self._writable()
        truth = self.truth
        n = self.n_lv
        ld = np.asarray(light_dir, np.float64)
        vd = np.asarray(view_dir, np.float64)
        li = np.asarray(lv_index)
        for name, a in (("light_dir", ld), ("view_dir", vd), ("lv_index", li)):
            if a.shape != (n, 3):
                raise ValueError(f"truth {name}: expected shape ({n}, 3), got {a.shape}")
        for name, a in (("light_dir", ld), ("view_dir", vd)):
            norm = np.linalg.norm(a, axis=1)
            bad = np.flatnonzero(~np.isfinite(norm) | (np.abs(norm - 1) > ROTATION_TOL))
            if len(bad):
                raise ValueError(f"truth {name}: rows {bad[:MAX_LISTED].tolist()} are not finite unit vectors")
        want = _lv_index(self.n_turn, self.n_cam, self.n_leds)
        bad = np.flatnonzero((li != want).any(axis=1))
        if len(bad):
            raise ValueError(
                f"truth lv_index: rows {bad[:MAX_LISTED].tolist()} differ from the row-major "
                "(turntable, camera, led) order")
        write_chunk_aligned(truth["light_dir"], ..., ld)
        write_chunk_aligned(truth["view_dir"], ..., vd)
        write_chunk_aligned(truth["lv_index"], ..., want)

    def write_truth_map(self, name: str, data: np.ndarray) -> zarr.Array:
        """Write a material map ``truth/maps_<name>`` (one chunk, overwritten).

        Parameters
        ----------
        name : str
            Map name, e.g. ``"albedo"``; stored as ``maps_albedo``.
        data : (h, w) or (h, w, k) ndarray
        """
        self._writable()
        data = np.asarray(data)
        if data.dtype.kind == "f" and not np.isfinite(data).all():
            raise ValueError(f"truth map {name!r} holds NaN/Inf")
        key = name if name.startswith("maps_") else f"maps_{name}"
        arr = create_array(self.truth,
            key, shape=data.shape, dtype=data.dtype, chunks=tuple(max(1, s) for s in data.shape),
            fill_value=0, compressors=None, overwrite=True,
            dimension_names=["tex_row", "tex_col", "channel"][: data.ndim] if data.ndim <= 3 else None,
        )
        arr[...] = data
        return arr

    def set_truth_material(self, material: Mapping[str, Any]) -> None:
        """Store the material description as plain-JSON attrs of ``truth/``."""
        self._writable()
        self.truth.attrs.update({"material": to_json_attr(dict(material), "material")})

    def mark_complete(self) -> None:
        """Validate the whole store and set ``complete`` to true.

        Raises
        ------
        CaptureStoreError
            Naming the missing ``(t, c, i)`` brackets (and anything else wrong).
        """
        self._writable()
        problems = _validate_group(self.group, require_complete=True, check_flag=False)
        if problems:
            raise CaptureStoreError(self.path, problems)
        self.group.attrs["complete"] = True
