"""Capture store: the on-disk form of one camera-dome capture (schema ``btf-capture`` 1.0,
docs/capture-store.md), created and opened here.

A capture store is a Zarr v3 group holding the raw Bayer exposure brackets of every view under
every illumination pattern, the exposure times, the illumination patterns, the device geometry and
calibration, dark frames, resume markers and, for simulated captures, the exact ground truth.

- :mod:`tasks.stores.capture_schema`: names, units, the array table, :class:`CaptureMetadata`;
- :mod:`tasks.stores.capture_validate`: every check, all problems listed at once;
- :mod:`tasks.stores.capture_store`: :class:`CaptureStore`, reading and whole-chunk writing;
- this module: :func:`create_capture_store` (validates the metadata first, resumes an unfinished
  store of the same configuration, builds an ``overwrite`` beside the old store),
  :func:`commit_capture`, :func:`check_capture_target` and :func:`open_capture_store`.

Examples
--------
>>> store = create_capture_store("cap.zarr", meta)            # doctest: +SKIP
>>> for t, c in store.pending_views():                        # doctest: +SKIP
...     store.write_bracket(t, c, frames, exposure_time)
>>> store = commit_capture(store, "cap.zarr", "simulate")     # doctest: +SKIP
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from collections.abc import Mapping
from typing import Any

import numpy as np
import zarr

import btfcore
from tasks.integrity import create_array
from pathlib import Path

from tasks.staging import (
    begin_store,
    commit_staged,
    finish_interrupted_commit,
    finish_store,
    staging_path,
    store_attrs,
)
from tasks.stores.capture_store import CaptureStore
from tasks.stores.capture_schema import (  # noqa: F401 - the schema's names are the capture store's
    ARRAYS,
    BAYER_PATTERNS,
    FIXED_SIZES,
    LV_ORDER,
    META_ARRAY_FIELDS,
    META_ATTR_FIELDS,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    SENSOR_KEYS,
    TRUTH_ARRAYS,
    UNITS,
    CaptureMetadata,
    CaptureStoreError,
    expected_chunks,
    raw_spec,
)
from tasks.stores.capture_validate import (
    ArrayInfo,
    AxisSizes,
    check_attrs,
    check_content,
    check_shapes,
    validate_capture_store,
)
from tasks.stores.common import ROOT_ATTRS, Problem, is_url, to_json_attr

__all__ = [
    "BAYER_PATTERNS",
    "LV_ORDER",
    "SCHEMA_NAME",
    "SCHEMA_VERSION",
    "UNITS",
    "CaptureMetadata",
    "CaptureStore",
    "CaptureStoreError",
    "capture_target",
    "check_capture_target",
    "commit_capture",
    "create_capture_store",
    "finished_capture",
    "open_capture_store",
    "reusable_capture",
    "validate_capture_store",
]


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
        return [Problem(ROOT_ATTRS, None, "plain-JSON metadata without NaN/Inf", str(e),
                        "convert the value (unknowns are null)")], None, {}
    check_attrs(attrs, problems, in_memory=True)
    arrays: dict[str, np.ndarray] = {}
    infos: dict[str, ArrayInfo] = {}
    for name in META_ARRAY_FIELDS:
        dtype = ARRAYS[name][0]
        try:
            a = np.asarray(getattr(meta, name))
            if a.dtype.kind not in "biuf":
                raise TypeError(f"dtype {a.dtype}")
            arrays[name] = a.astype(np.float64)  # checks run on exact values
        except (TypeError, ValueError) as e:
            problems.append(Problem(name, None, f"a numeric array castable to {dtype}",
                                    str(e), f"pass {name} as a numpy array"))
            continue
        infos[name] = ArrayInfo(a.shape, dtype, None, None, (lambda v=arrays[name]: v))
    sizes = AxisSizes()
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
    usable = check_shapes(infos, sizes, problems, check_layout=False)
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
    check_content(infos, usable, sizes, attrs, problems, planned=planned)
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
        Replace whatever is at ``path``: the new store is built beside it at
        :func:`tasks.staging.staging_path` (``X.partial.zarr``) and :func:`commit_capture` puts it
        in place once it is complete, so that a failed run leaves the old store whole.

    Returns
    -------
    CaptureStore
        Opened with mode ``"r+"``; its ``path`` is the staging store when it replaces one
        (:func:`capture_target`).

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
    :meth:`CaptureStore.pending_views` lists the rest. So is the staging store of a killed
    ``overwrite`` of the same configuration, with or without ``overwrite``.
    """
    problems, attrs, arrays = _meta_problems(meta)
    if problems:
        raise CaptureStoreError(path, problems)
    assert attrs is not None
    target, fresh = capture_target(path, attrs["provenance"]["config_hash"], overwrite)
    if not fresh:
        if os.fspath(target) != os.fspath(path) and store_attrs(target).get("complete"):
            return CaptureStore(target, "r+")           # a replacement killed before its commit
        existing = _existing_store(target, meta, attrs, with_truth)
        if existing is not None:
            return existing
    path = target
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
    """Raise what a run writing ``meta``'s capture to ``path`` (without ``overwrite``) refuses, writing nothing.

    A complete store of the same configuration is finished work (:func:`finished_capture`), and the
    staging store of a killed ``overwrite`` of it resumes: neither is refused.

    Raises
    ------
    CaptureStoreError
        ``meta`` violates the schema.
    FileExistsError
        ``path`` holds a store of another config, an unfinished one of other metadata, or something else.
    """
    problems, attrs, _ = _meta_problems(meta)
    if problems:
        raise CaptureStoreError(path, problems)
    key = attrs["provenance"]["config_hash"]
    if not _staged_replacement(path, key) and finished_capture(path, key) is None:
        _existing_store(path, meta, attrs, with_truth)


def finished_capture(path: str | os.PathLike, key: str) -> CaptureStore | None:
    """The complete capture store of config ``key`` at ``path`` (opened read-only), else ``None``."""
    if not is_url(path) and not os.path.exists(path):
        return None
    try:
        store = open_capture_store(path, mode="r", require_complete=True)
    except Exception:  # noqa: BLE001 - anything else at path is for the caller's checks to name
        return None
    return store if (store.attrs.get("provenance") or {}).get("config_hash") == key else None


def reusable_capture(path: str | os.PathLike, key: str, overwrite: bool) -> CaptureStore | None:
    """The complete capture of config ``key`` at ``path`` that a run leaves alone (finished work), else
    ``None``: the run has views to write (a new, unfinished or staged store, or ``overwrite``).
    An interrupted commit into ``path`` is finished first (:func:`capture_target`)."""
    target, fresh = capture_target(path, key, overwrite)
    same = os.fspath(target) == os.fspath(path)
    return finished_capture(path, key) if same and not fresh else None


def _staged_replacement(path: str | os.PathLike, key: str) -> bool:
    """Whether the staging store beside ``path`` holds a capture of config ``key`` (a killed ``overwrite``)."""
    if is_url(path):
        return False
    return ((store_attrs(staging_path(path)) or {}).get("provenance") or {}).get("config_hash") == key


def capture_target(path: str | os.PathLike, key: str, overwrite: bool) -> tuple[str | os.PathLike, bool]:
    """Where a capture of config ``key`` for ``path`` is written, and whether it is built afresh.

    An interrupted commit into ``path`` is finished first (:func:`tasks.staging.finish_interrupted_commit`).
    Then the staging store beside ``path`` when it holds this config (a killed ``overwrite`` resumes, with or
    without ``overwrite``), or when ``overwrite`` replaces a store at ``path`` (built afresh there); else
    ``path`` itself (afresh only with ``overwrite``: nothing is there to keep). A URL store is written in place.
    """
    if is_url(path):
        return path, overwrite
    finish_interrupted_commit(path)
    staging = staging_path(path)
    if _staged_replacement(path, key):
        return staging, False
    if overwrite and store_attrs(path) is not None and not (os.path.isdir(path) and not os.listdir(path)):
        return staging, True
    return path, overwrite


def commit_capture(store: CaptureStore, path: str | os.PathLike, command: str) -> CaptureStore:
    """Mark the written ``store`` complete and, when it is the staging store of ``path``, put it in place.

    ``command`` (``"simulate"``, ``"import-raw"``) names the run in the messages of
    :func:`tasks.staging.commit_staged`. Returns the complete store at ``path``, opened read-only.
    """
    if not store.complete:
        store.mark_complete()
    if not is_url(path) and Path(store.path) != Path(path):
        commit_staged(path, command)
    return open_capture_store(path)


def _existing_store(path, meta: CaptureMetadata, attrs: dict, with_truth: bool) -> CaptureStore | None:
    if is_url(path):
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
        if not old and set(found.keys()) <= {*ARRAYS, "truth", "plan"}:
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
    for f in META_ATTR_FIELDS:
        va, vb = to_json_attr(getattr(a, f)), to_json_attr(getattr(b, f))
        if f == "sensor":
            va = {k: va.get(k) for k in SENSOR_KEYS}
            vb = {k: (vb or {}).get(k) for k in SENSOR_KEYS}
        if va != vb:
            out.append(f"{f}: {va!r} != {vb!r}")
    for f in META_ARRAY_FIELDS:
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
    n_turn, n_cam, n_illum, n_exp, rows, cols = meta.raw_shape[:6]
    sizes = {
        "turntable": n_turn, "camera": n_cam, "illumination": n_illum, "exposure": n_exp,
        "row": rows, "col": cols, "led": meta.n_leds, "dark": meta.n_dark,
        "lv": meta.n_lv, **FIXED_SIZES,
    }
    if with_truth:
        h, w = map(int, meta.texture_shape)
        sizes.update(tex_row=h, tex_col=w, tex2_row=2 * h, tex2_col=2 * w)

    def make(g: zarr.Group, name: str, spec, data: np.ndarray | None = None):
        dtype, axes, rule = spec
        shape = tuple(sizes[k] for _, k in axes)
        arr = create_array(g,
            name.split("/")[-1], shape=shape, dtype=dtype,
            chunks=expected_chunks(rule, shape, sizes), fill_value=0,
            dimension_names=[d for d, _ in axes], compressors=None,
        )
        if data is not None and data.size:
            arr[...] = data.astype(dtype)
        return arr

    for name, spec in ARRAYS.items():
        make(group, name, raw_spec(meta.bayer_pattern) if name == "raw" else spec, arrays.get(name))
    if with_truth:
        tg = group.create_group("truth")
        for name, spec in TRUTH_ARRAYS.items():
            make(tg, name, spec)


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
