"""Checking a capture store against the ``btf-capture`` schema (:mod:`tasks.stores.capture_schema`),
listing every problem at once: root attributes, array shapes and chunking, the values of the small
arrays, chunk files of written brackets, and completeness (docs/capture-store.md, "Validation").

Only the attributes and the small arrays are read, never the frames. The same checks run on
in-memory :class:`~tasks.stores.capture_schema.CaptureMetadata` before a store is created
(:func:`tasks.stores.capture.create_capture_store`).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr

from tasks.integrity import CorruptChunkError, chunk_files_exist
from tasks.stores.capture_schema import (
    ARRAYS,
    BAYER_PATTERNS,
    FIXED_SIZES,
    HOMOGRAPHY_MAX_COND,
    LV_ORDER,
    ROTATION_TOL,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    SENSOR_KEYS,
    SOURCES,
    TRUTH_ARRAYS,
    UNITS,
    RAW_RGB_SPEC,
    RESPONSE_SPEC,
    RGB_PATTERN,
    expected_chunks,
    row_major_lv_index,
    trailing_steps_filled,
)
from tasks.stores.common import MAX_LISTED, ROOT_ATTRS, WHOLE_STORE, Problem, fmt_idx, is_url, listing, store_arg


def _nonfinite(name: str, arr: np.ndarray, axes: str, hint: str) -> list[Problem]:
    bad = ~np.isfinite(arr)
    if not bad.any():
        return []
    idx = np.argwhere(bad)
    return [Problem(
        name, f"{axes}={listing(idx, 5)}", "finite values",
        f"{len(idx)} NaN/Inf value(s)", hint,
    )]


@dataclass
class ArrayInfo:
    """What validation needs to know about one array, without its data."""

    shape: tuple[int, ...]
    dtype: str
    chunks: tuple[int, ...] | None
    dims: tuple[str, ...] | None
    load: Callable[[], np.ndarray] | None  # None: do not read (big or not yet there)


class AxisSizes:
    """Axis lengths taken from the first array that has them."""

    def __init__(self) -> None:
        self.value: dict[str, int] = dict(FIXED_SIZES)
        self.source: dict[str, str] = {k: "the schema" for k in FIXED_SIZES}

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


def check_attrs(attrs: Mapping[str, Any], problems: list[Problem], *, in_memory: bool = False) -> None:
    """Root attribute checks (shared by stores and in-memory metadata)."""
    P = problems.append
    recreate = "recreate the store with btf-pipeline (create_capture_store)"

    def get(key):
        if key not in attrs:
            P(Problem(ROOT_ATTRS, key, f"attribute {key!r}", "nothing",
                      f"the store is missing root attribute {key!r}; {recreate}"))
            return None, False
        return attrs[key], True

    if not in_memory:
        v, ok = get("schema")
        if ok and v != SCHEMA_NAME:
            P(Problem(ROOT_ATTRS, "schema", repr(SCHEMA_NAME), repr(v),
                      "this is not a capture store; open it with the reader for its schema"))
        v, ok = get("schema_version")
        if ok and v != SCHEMA_VERSION:
            P(Problem(ROOT_ATTRS, "schema_version", repr(SCHEMA_VERSION), repr(v),
                      f"this code reads {SCHEMA_NAME} {SCHEMA_VERSION}; use the btf-pipeline "
                      "version that wrote the store or migrate it"))

    v, ok = get("device")
    if ok and (not isinstance(v, str) or not v):
        P(Problem(ROOT_ATTRS, "device", "a non-empty string", repr(v), "set the device name"))

    v, ok = get("bayer_pattern")
    if ok and v not in BAYER_PATTERNS + (RGB_PATTERN,):
        P(Problem(ROOT_ATTRS, "bayer_pattern", f"one of {', '.join(BAYER_PATTERNS + (RGB_PATTERN,))}", repr(v),
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
                P(Problem(ROOT_ATTRS, key, "an integer", repr(v), f"store {key} as an integer DN"))
    bd = levels.get("bit_depth")
    if bd is not None and not 1 <= bd <= 16:
        P(Problem(ROOT_ATTRS, "bit_depth", "1..16 (raw is uint16)", repr(bd),
                  "set the ADC bit depth of the sensor"))
        bd = None
    bl, wl = levels.get("black_level"), levels.get("white_level")
    if bl is not None and bl < 0:
        P(Problem(ROOT_ATTRS, "black_level", ">= 0", repr(bl), "check the sensor black level"))
    if bl is not None and wl is not None and bl >= wl:
        P(Problem(ROOT_ATTRS, "black_level", f"black_level < white_level ({wl})", repr(bl),
                  "check the sensor calibration: black level must lie below the saturation level"))
    if wl is not None and bd is not None and wl > 2**bd - 1:
        P(Problem(ROOT_ATTRS, "white_level", f"<= 2**bit_depth - 1 = {2**bd - 1}", repr(wl),
                  "check white_level and bit_depth against the camera's raw format"))

    v, ok = get("sensor")
    if ok:
        if not isinstance(v, Mapping):
            P(Problem(ROOT_ATTRS, "sensor", f"a dict with keys {list(SENSOR_KEYS)}", repr(v),
                      "store the sensor noise parameters (null where unknown)"))
        else:
            for k in SENSOR_KEYS:
                if k not in v:
                    P(Problem(ROOT_ATTRS, f"sensor.{k}", "a float or null", "nothing",
                              "add the key (null when unknown)"))
                    continue
                x = v[k]
                if x is None:
                    continue
                if (not isinstance(x, (int, float)) or isinstance(x, bool)
                        or not math.isfinite(x)):
                    P(Problem(ROOT_ATTRS, f"sensor.{k}", "a finite float or null", repr(x),
                              "store a calibrated value or null"))
                elif (x < 0) if k in ("read_noise_e", "dark_current_e_per_s") else (x <= 0):
                    P(Problem(ROOT_ATTRS, f"sensor.{k}",
                              ">= 0" if k in ("read_noise_e", "dark_current_e_per_s") else "> 0",
                              repr(x), "check the sensor calibration"))

    v, ok = get("sample_size_m")
    if ok and (not isinstance(v, (int, float)) or isinstance(v, bool)
               or not math.isfinite(v) or v <= 0):
        P(Problem(ROOT_ATTRS, "sample_size_m", "a positive number of metres", repr(v),
                  "set the side length of the square sample in metres"))

    v, ok = get("texture_shape")
    if ok and not (isinstance(v, (list, tuple)) and len(v) == 2
                   and all(is_int(x) and x > 0 for x in v)):
        P(Problem(ROOT_ATTRS, "texture_shape", "[h, w], two positive integers", repr(v),
                  "set the rectified texture size"))

    if not in_memory:
        v, ok = get("lv_order")
        if ok and not (isinstance(v, (list, tuple)) and list(v) == LV_ORDER):
            P(Problem(ROOT_ATTRS, "lv_order", repr(LV_ORDER), repr(v),
                      "light/view pairs must be flattened row-major over "
                      "(turntable, camera, light); recreate the store"))
        v, ok = get("units")
        if ok and not (isinstance(v, Mapping) and all(v.get(k) == u for k, u in UNITS.items())):
            P(Problem(ROOT_ATTRS, "units", repr(UNITS), repr(v),
                      "convert the arrays to these units and recreate the store"))
        v, ok = get("complete")
        if ok and not isinstance(v, bool):
            P(Problem(ROOT_ATTRS, "complete", "true or false", repr(v), recreate))

    v, ok = get("provenance")
    if ok:
        if not isinstance(v, Mapping):
            P(Problem(ROOT_ATTRS, "provenance", "a dict", repr(v), recreate))
        else:
            _check_provenance(v, problems)


def _check_provenance(prov: Mapping[str, Any], problems: list[Problem]) -> None:
    P = problems.append
    for key in ("code_version", "config_hash"):
        x = prov.get(key)
        if not isinstance(x, str) or not x:
            P(Problem(ROOT_ATTRS, f"provenance.{key}", "a non-empty string",
                      "nothing" if key not in prov else repr(x),
                      "the producing flow must record it (it keys resume and caches)"))
    if "seed" not in prov:
        P(Problem(ROOT_ATTRS, "provenance.seed", "an integer or null", "nothing",
                  "record the random seed (null for real captures)"))
    elif prov["seed"] is not None and (not isinstance(prov["seed"], int) or isinstance(prov["seed"], bool)):
        P(Problem(ROOT_ATTRS, "provenance.seed", "an integer or null", repr(prov["seed"]),
                  "record the random seed (null for real captures)"))
    created = prov.get("created")
    ok = isinstance(created, str)
    if ok:
        try:
            _dt.datetime.fromisoformat(created)
        except ValueError:
            ok = False
    if not ok:
        P(Problem(ROOT_ATTRS, "provenance.created", "an ISO 8601 timestamp",
                  "nothing" if "created" not in prov else repr(created),
                  "record the creation time, e.g. datetime.now(timezone.utc).isoformat()"))
    if prov.get("source") not in SOURCES:
        P(Problem(ROOT_ATTRS, "provenance.source", f"one of {list(SOURCES)}",
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


def check_shapes(
    infos: Mapping[str, ArrayInfo], sizes: AxisSizes, problems: list[Problem],
    *, check_layout: bool = True,
) -> dict[str, bool]:
    """Dtypes, dimensions, shapes and chunking; returns which arrays are usable."""
    usable: dict[str, bool] = {}
    spec_all = {**ARRAYS, **TRUTH_ARRAYS}
    order = list(ARRAYS) + list(TRUTH_ARRAYS)
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
        if name == "raw" and len(info.shape) == len(RAW_RGB_SPEC[1]):     # an "RGB" capture (btf import-images)
            dtype, axes, chunk_rule = RAW_RGB_SPEC
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
                want = expected_chunks(chunk_rule, info.shape, sizes.value)
                if tuple(info.chunks) != want:
                    problems.append(Problem(
                        name, "chunks", f"chunks {want}", f"chunks {tuple(info.chunks)}",
                        "writers own whole chunks of exactly this layout; recreate the store "
                        "with create_capture_store"))
    return usable


_CALIB = "check the device calibration that produced it"


def check_content(
    infos: Mapping[str, ArrayInfo], usable: Mapping[str, bool], sizes: AxisSizes,
    attrs: Mapping[str, Any], problems: list[Problem], *, planned: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Value checks on the small arrays, one concern after the other. Returns the loaded arrays.

    ``planned`` (a plan capture, ``plan/shot >= 0``): brackets may end in exposure times of 0
    (steps the plan does not take).
    """
    data = _load_small_arrays(infos, usable, problems)
    _check_markers(data, problems)
    _check_exposure_times(data, problems, planned)
    _check_illumination(data, problems)
    _check_leds(data, problems)
    _check_cameras(data, problems)
    _check_homographies(data, attrs, sizes, problems)
    _check_dark_frames(data, problems)
    _check_truth_directions(data, sizes, problems)
    return data


def _load_small_arrays(infos: Mapping[str, ArrayInfo], usable: Mapping[str, bool],
                       problems: list[Problem]) -> dict[str, np.ndarray]:
    """The arrays that are small enough to check by value; a chunk that does not read back is a problem."""
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
    return data


def _check_markers(data: Mapping[str, np.ndarray], problems: list[Problem]) -> None:
    """``written``: resume markers are 0 or 1."""
    written = data.get("written")
    if written is not None:
        bad = ~np.isin(written, (0, 1))
        if bad.any():
            problems.append(Problem("written", f"(t, c, i)={listing(np.argwhere(bad))}", "0 or 1",
                                    f"{int(bad.sum())} other value(s)",
                                    "the resume markers are corrupt; recreate the store"))


def _check_exposure_times(data: Mapping[str, np.ndarray], problems: list[Problem], planned: np.ndarray | None) -> None:
    """``exposure_time``: finite, > 0 and strictly increasing in every written bracket (a plan capture's
    shorter brackets end in 0 s)."""
    written = data.get("written")
    P = problems.append
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
            P(Problem("exposure_time", f"(t, c, i)={listing(nf)}", "finite exposure times",
                      f"NaN/Inf in {len(nf)} bracket(s)", hint))
        pos = (et > 0).all(axis=-1)
        nonpos = np.argwhere(mask & fin & ~pos)
        if len(nonpos):
            first = tuple(nonpos[0])
            P(Problem("exposure_time", f"(t, c, i)={listing(nonpos)}", "all exposure times > 0 s",
                      f"{len(nonpos)} bracket(s) with a time <= 0, e.g. {et[first].tolist()} at "
                      f"{fmt_idx(first)}", hint))
        with np.errstate(invalid="ignore"):
            inc = (np.diff(et, axis=-1) > 0).all(axis=-1)
        noninc = np.argwhere(mask & fin & pos & ~inc)
        if len(noninc):
            first = tuple(noninc[0])
            P(Problem("exposure_time", f"(t, c, i)={listing(noninc)}",
                      "strictly increasing times along the exposure axis",
                      f"{len(noninc)} bracket(s) not increasing, e.g. {et[first].tolist()} at "
                      f"{fmt_idx(first)}", hint))


def _check_illumination(data: Mapping[str, np.ndarray], problems: list[Problem]) -> None:
    """``illumination``: binary LED states, at least one LED on per pattern."""
    P = problems.append
    il = data.get("illumination")
    if il is not None:
        bad = ~np.isin(il, (0, 1))
        if bad.any():
            P(Problem("illumination", f"(illum, led)={listing(np.argwhere(bad))}",
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


def _check_leds(data: Mapping[str, np.ndarray], problems: list[Problem]) -> None:
    """``led_position``: finite, above the sample plane."""
    P = problems.append
    lp = data.get("led_position")
    if lp is not None:
        problems += _nonfinite("led_position", lp, "(led, xyz)", _CALIB)
        z = lp[:, 2]
        low = np.flatnonzero(np.isfinite(z) & (z <= 0))
        if len(low):
            P(Problem("led_position", f"led {', '.join(map(str, low[:MAX_LISTED].tolist()))}",
                      "z > 0 m (LEDs above the sample plane, z up)",
                      f"z = {z[low[:5]].tolist()}",
                      "positions must be in metres in the world frame with z up and the sample "
                      "centre at the origin; " + _CALIB))


def _check_cameras(data: Mapping[str, np.ndarray], problems: list[Problem]) -> None:
    """``camera_K`` (an intrinsic matrix), ``camera_R`` (a rotation), ``camera_t``, ``turntable_angle``: finite."""
    P = problems.append
    K = data.get("camera_K")
    if K is not None:
        problems += _nonfinite("camera_K", K, "(camera, i, j)", _CALIB)
        for c in range(K.shape[0]):
            k = K[c]
            if not np.isfinite(k).all():
                continue
            if not (np.allclose(k[2], (0, 0, 1), atol=1e-9) and np.allclose(k[1, 0], 0)
                    and k[0, 0] > 0 and k[1, 1] > 0):
                P(Problem("camera_K", f"camera {c}",
                          "[[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0",
                          repr(np.round(k, 6).tolist()), _CALIB))
    R = data.get("camera_R")
    if R is not None:
        problems += _nonfinite("camera_R", R, "(camera, i, j)", _CALIB)
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
        problems += _nonfinite("camera_t", ct, "(camera, xyz)", _CALIB)
    ta = data.get("turntable_angle")
    if ta is not None:
        problems += _nonfinite("turntable_angle", ta, "(turntable,)", _CALIB)   # the dome's, not the manifest's


def _check_homographies(data: Mapping[str, np.ndarray], attrs: Mapping[str, Any], sizes: AxisSizes,
                        problems: list[Problem]) -> None:
    """``homography``: invertible, mapping the sample's corners inside the raw frame."""
    P = problems.append
    H = data.get("homography")
    if H is not None:
        problems += _nonfinite("homography", H, "(t, c, i, j)", _CALIB)
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
            P(Problem("homography", "(t, c)=" + ", ".join(fmt_idx(i) for i, _ in singular[:MAX_LISTED])
                      + (f" (+{len(singular) - MAX_LISTED} more)" if len(singular) > MAX_LISTED else ""),
                      f"an invertible 3x3 matrix (condition number <= {HOMOGRAPHY_MAX_COND:g})",
                      f"condition number {singular[0][1]:.3g} at {fmt_idx(singular[0][0])}",
                      "recompute the homography from the camera calibration and turntable "
                      "angle (H = K [r1 r2 t] in the sample frame)"))
        if outside:
            P(Problem("homography", "(t, c)=" + ", ".join(fmt_idx(i) for i, _ in outside[:MAX_LISTED])
                      + (f" (+{len(outside) - MAX_LISTED} more)" if len(outside) > MAX_LISTED else ""),
                      f"the sample corners (+-s/2, +-s/2) with s = {s} m mapped inside the "
                      f"{rows}x{cols} raw frame",
                      f"{outside[0][1]} at {fmt_idx(outside[0][0])}",
                      "check sample_size_m (metres), the ROI offset in camera_K / homography, "
                      "and that the homography maps sample (x, y) to raw (col, row)"))


def _check_dark_frames(data: Mapping[str, np.ndarray], problems: list[Problem]) -> None:
    """``dark_exposure_time`` (finite, > 0, increasing) and ``dark_written`` (0 or 1)."""
    P = problems.append
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


def _check_truth_directions(data: Mapping[str, np.ndarray], sizes: AxisSizes, problems: list[Problem]) -> None:
    """``truth/light_dir``, ``truth/view_dir`` (unit vectors) and ``truth/lv_index`` (row-major), once written."""
    P = problems.append
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
        want = row_major_lv_index(sizes.value.get("turntable", 0), sizes.value.get("camera", 0),
                                  sizes.value.get("led", 0))
        if want.shape == li.shape:
            bad = np.flatnonzero((li != want).any(axis=1))
            if len(bad):
                P(Problem("truth/lv_index", f"lv {', '.join(map(str, bad[:MAX_LISTED].tolist()))}",
                          "(turntable, camera, led) in row-major order (lv_order)",
                          f"{li[bad[0]].tolist()} at lv {bad[0]}",
                          "flatten light/view pairs row-major over (turntable, camera, led)"))


def _directions_written(ld: np.ndarray, vd: np.ndarray) -> bool:
    return bool(np.any(ld != 0) or np.any(vd != 0))


def _check_completeness(
    data: Mapping[str, np.ndarray], attrs: Mapping[str, Any], sizes: AxisSizes,
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
                P = Problem("written", f"(t, c, i)={listing(miss)}",
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
                    "truth/written", f"(t, c)={listing(miss)}", "ground truth written for every view",
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
            ROOT_ATTRS, "complete", "true", repr(attrs.get("complete")),
            "every bracket is written but the store was never marked complete: call "
            "CaptureStore.mark_complete() (or " + hint + ")"))


def _array_info(arr: zarr.Array, *, load: bool) -> ArrayInfo:
    dims = arr.metadata.dimension_names if hasattr(arr.metadata, "dimension_names") else None
    return ArrayInfo(
        shape=tuple(int(s) for s in arr.shape),
        dtype=str(arr.dtype),
        chunks=tuple(int(c) for c in arr.chunks),
        dims=tuple(dims) if dims is not None else None,
        load=(lambda a=arr: a[...]) if load else None,
    )


_BIG = ("raw", "dark_frames", "truth/btf", "truth/btf_2x")


def validate_group(
    group: zarr.Group, *, require_complete: bool, check_flag: bool = True,
) -> list[Problem]:
    problems: list[Problem] = []
    attrs = dict(group.attrs)
    other = attrs.get("schema")
    if isinstance(other, str) and other != SCHEMA_NAME:
        # another kind of store (e.g. a btf-texture store): one problem, not a list of everything missing
        return [Problem("attrs", "schema", repr(SCHEMA_NAME), repr(other),
                        "this is not a capture store; give the capture store (btf simulate / btf import-raw output)")]
    check_attrs(attrs, problems)

    members = dict(group.members(max_depth=None))
    infos: dict[str, ArrayInfo] = {}
    for name in ARRAYS:
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
            for name in TRUTH_ARRAYS:
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
    sizes = AxisSizes()
    ts = attrs.get("texture_shape")
    if isinstance(ts, list) and len(ts) == 2 and all(isinstance(x, int) and x > 0 for x in ts):
        sizes.seed("tex_row", ts[0], "attrs['texture_shape'][0]")
        sizes.seed("tex_col", ts[1], "attrs['texture_shape'][1]")
        sizes.seed("tex2_row", 2 * ts[0], "2 * attrs['texture_shape'][0]")
        sizes.seed("tex2_col", 2 * ts[1], "2 * attrs['texture_shape'][1]")
    usable = check_shapes(infos, sizes, problems)
    _check_rgb_capture(members, infos, attrs, problems)
    data = check_content(infos, usable, sizes, attrs, problems, planned=planned)
    _check_chunk_files(group, data, attrs, problems)
    _check_completeness(data, attrs, sizes, problems,
                        require_complete=require_complete, check_flag=check_flag, planned=planned)
    return problems


def _check_rgb_capture(members: Mapping[str, Any], infos: Mapping[str, ArrayInfo], attrs: Mapping[str, Any],
                       problems: list[Problem]) -> None:
    """An ``"RGB"`` capture (``btf import-images``) has ``raw``'s channel axis and ``response`` ``(n_cam,
    2**bit_depth, 3)``, finite and >= 0; a Bayer capture has no channel axis."""
    rgb, raw, node = attrs.get("bayer_pattern") == RGB_PATTERN, infos.get("raw"), members.get("response")
    fix = "recreate the store (btf import-images --overwrite, or give --response FILE)"
    if raw is not None and rgb != (len(raw.shape) == len(RAW_RGB_SPEC[1])):
        problems.append(Problem("raw", None, "a channel axis of 3 exactly when bayer_pattern is 'RGB'",
                                f"shape {raw.shape}, bayer_pattern {attrs.get('bayer_pattern')!r}", fix))
    if not rgb:
        return
    bd, n_cam = attrs.get("bit_depth"), raw.shape[1] if raw is not None else None
    want = (n_cam, 2 ** bd if isinstance(bd, int) else None, 3)
    if node is None and attrs.get("complete") is not True:
        return      # an import killed before writing it (it precedes every bracket): the resumed import writes it
    if not isinstance(node, zarr.Array) or str(node.dtype) != RESPONSE_SPEC[0] or tuple(node.shape) != want:
        found = "nothing" if not isinstance(node, zarr.Array) else f"{node.dtype} {tuple(node.shape)}"
        problems.append(Problem("response", None, f"{RESPONSE_SPEC[0]} {want} (camera, code, channel)", found, fix))
        return
    r = np.asarray(node[...])
    bad = np.argwhere(~(np.isfinite(r) & (r >= 0)))
    if bad.size:
        problems.append(Problem("response", fmt_idx(bad[0]), "finite and >= 0", repr(float(r[tuple(bad[0])])), fix))


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
                name, f"chunk {listing(np.array(missing))}",
                f"a chunk file for each bracket that {marker_name}{axes} = 1 marks as written",
                f"chunk file missing for {len(missing)} chunk(s) (Zarr would read them as zeros)",
                "the store was damaged after writing; write the capture again (`btf simulate --overwrite` / "
                "`btf import-raw --overwrite`) or restore it from a backup"))


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
    if not is_url(path) and not os.path.exists(os.fspath(path)):
        return [Problem(WHOLE_STORE, None, "a capture store directory", f"nothing at {os.fspath(path)!r}",
                        "check the path, or create the store (`btf simulate` / `btf ingest`)")]
    try:
        group = zarr.open_group(store_arg(path), mode="r", zarr_format=3)
    except Exception as e:  # noqa: BLE001 - any failure to open is one problem
        return [Problem(WHOLE_STORE, None, "a Zarr v3 group (zarr.json with node_type 'group')",
                        f"{type(e).__name__}: {e}",
                        "this is not a capture store; check the path")]
    return validate_group(group, require_complete=require_complete)
