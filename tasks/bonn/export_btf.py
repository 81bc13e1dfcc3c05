"""``btf export``: a finished btf-texture store -> a Bonn BTF file (DFMF, FMF or BDI; docs/bonn-formats.md,
"Exporting (btf export)").

The store's rows must form views x lights: a resampled store (``lv_order`` ``["view", "light"]``), an
imported one, or an ingested one (``["turntable", "camera", "light"]``: every (turntable, camera) pair is a
view with its own light directions in the sample frame; the formats store a light list per view). Every
view must have the same number of lights.

- DFMF: the store's linear RGB is encoded to the chosen colour model
  (:func:`btfcore.bonn.encode_colour`) and each channel's ``(n_lv, n_tx)`` matrix is factorised
  (:func:`btfcore.bonn.factorise`) with ``K`` components, by default all of them
  (``min(n_lv, n_tx)``: lossless up to the precision of the file).
- FMF: one factorisation of all channels (rows ``n_c * n_lv``, channel fastest), colour model 0.
- BDI: the textures themselves as half floats, written band by band from the store (bounded memory).

Half floats hold at most 65504: ``scale`` (``--scale F|auto``) writes the values times a factor, ``auto`` the
power of two that makes them fit when they do not (recorded in the file's XML).

The factorisations run in memory (``numpy``'s SVD of each channel): a store whose float32 textures exceed
:data:`MAX_FACTORISE_BYTES` is refused with a message pointing at BDI, which streams.

Nothing half-written ever lies at the output path: the file is written to ``<out>.partial`` beside it and
renamed into place once complete; an existing file is replaced only with ``overwrite``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from btfcore.bonn import COLOUR_MODELS, UnknownColourModelError, decode_colour, decode_textures, encode_colour, \
    factorise
from tasks.bonn.header import CommonHeader, make_header, sph_to_dir
from tasks.staging import write_file
from tasks.stores.btf import LV_ORDER, RESAMPLED_LV_ORDER, BtfStore, open_btf_store

__all__ = [
    "FORMATS",
    "MAX_FACTORISE_BYTES",
    "PRECISIONS",
    "SIGNATURE_OF",
    "ExportPlan",
    "check_export",
    "export_store",
    "header_for",
    "views_lights",
]

#: What ``--format`` takes.
FORMATS = ("dfmf", "fmf", "bdi")
#: ``--precision`` -> bytes per stored scalar of a factorised file.
PRECISIONS = {"half": 2, "single": 4}
#: The signature each format is written with (all with the rotations block).
SIGNATURE_OF = {"dfmf": "!DFMF08FCR", "fmf": "!FMF12FCER", "bdi": "!BDIF06R2!"}
#: BDI chunk compressions by name (the file's uint8 code).
BDI_COMPRESSIONS = {"raw": 0, "bzip2": 1, "sparse": 2}
#: Most bytes of float32 textures (``n_lv * h * w * 3 * 4``) a DFMF or FMF export factorises in memory;
#: the peak resident memory is about 5 times that for DFMF (textures, one float64 channel, the SVD's copies)
#: and 8 times for FMF (one float64 matrix of all channels), measured on a 267 MiB store.
MAX_FACTORISE_BYTES = 256 << 20
#: Largest finite half float: a factor value beyond it would be written as infinity.
HALF_MAX = float(np.finfo(np.float16).max)
#: Tolerance of "the rows of a view share one view direction".
VIEW_TOL = 1e-6
#: Bytes of float64 rows a DFMF/FMF export encodes or decodes at a time (colour model, error summary).
BLOCK_BYTES = 32 << 20
#: Bytes of store textures a BDI export reads at a time (whole scan-line chunks).
BDI_READ_BYTES = 64 << 20
#: ``--scale auto`` brings the largest value a half float must hold to at most this (a power of two below
#: :data:`HALF_MAX`, leaving headroom for the rounding of sums in readers).
AUTO_TARGET = 2.0**14
#: Colour models whose channels are linear in RGB: ``--scale auto`` may scale their factors.
LINEAR_MODELS = (0, 1, 3, 4)


@dataclass(frozen=True)
class ExportPlan:
    """What :func:`check_export` found: the store's rows as views x lights and the checked settings.

    Attributes
    ----------
    store : BtfStore
    out : Path
    format : str
        ``"dfmf"``, ``"fmf"`` or ``"bdi"``.
    order : (n_v * n_l,) ndarray of int
        Store row of file row ``l + n_l * v``.
    n_v, n_l : int
    scalar_size : int
        2 (half) or 4 (single).
    colour_model : int
    components : int
        ``K`` of every factorisation (DFMF, FMF), 0 for BDI.
    compression : int
        BDI chunk compression code.
    scale : float or None
        The file's values are the store's times ``scale``; None: ``--scale auto``.
    basis : ndarray or None
        ``(n_lv, k)`` float64 model basis in file row order (``--basis``), else None.
    basis_name : str
        Where the basis came from (``MODEL/classes/CLS/als``), for the XML.
    """

    store: BtfStore
    out: Path
    format: str
    order: np.ndarray
    n_v: int
    n_l: int
    scalar_size: int
    colour_model: int
    components: int
    compression: int
    scale: float | None = 1.0
    basis: np.ndarray | None = None
    basis_name: str = ""


def views_lights(store: BtfStore) -> tuple[np.ndarray, int, int]:
    """The store's rows as a views x lights grid.

    Parameters
    ----------
    store : BtfStore

    Returns
    -------
    order : (n_v * n_l,) ndarray of int
        Store row of file row ``l + n_l * v`` (view-major, light fastest).
    n_v, n_l : int

    Raises
    ------
    ValueError
        The rows are not a full grid of views x lights, views differ in their number of lights, or the
        rows of one view do not share a view direction; the message names the store, the row and the fix.
    """
    attrs = store.attrs
    lv_order = attrs.get("lv_order")
    hint = ("export a resampled store (`btf resample`), an imported one (`btf import-btf`) or one from `btf "
            "ingest`")
    if "lv_index" not in store.group:
        raise ValueError(f"{store.path}: no lv_index array, so its rows cannot be arranged as views x lights; {hint}")
    index = np.asarray(store.lv_index, dtype=np.int64)
    if lv_order == RESAMPLED_LV_ORDER and index.shape == (store.n_lv, 2):
        view, light = index[:, 0], index[:, 1]
    elif lv_order == LV_ORDER and index.shape == (store.n_lv, 3):
        n_cam = int(index[:, 1].max()) + 1
        view, light = index[:, 0] * n_cam + index[:, 1], index[:, 2]
    else:
        raise ValueError(f"{store.path}: rows ordered {lv_order!r} with lv_index of shape {index.shape} are not views "
                         f"x lights ({RESAMPLED_LV_ORDER!r} or {LV_ORDER!r}); {hint}")
    if index.min(initial=0) < 0:
        raise ValueError(f"{store.path}: lv_index holds negative indices; {hint}")
    counts = np.bincount(view)
    present = np.flatnonzero(counts)
    if len(present) and len(set(counts[present].tolist())) > 1:
        small, large = int(present[np.argmin(counts[present])]), int(present[np.argmax(counts[present])])
        raise ValueError(f"{store.path}: views have different numbers of lights (view {large}: {counts[large]}, view "
                         f"{small}: {counts[small]}); the Bonn formats store a light list per view, but btf.hh and "
                         "most readers use the first view's for all: resample the store to one sampling first "
                         "(`btf resample`)")
    n_v, n_l = int(view.max()) + 1, int(light.max()) + 1
    order = np.lexsort((light, view))
    grid = view[order] * n_l + light[order]
    if n_v * n_l != store.n_lv or not np.array_equal(grid, np.arange(store.n_lv)):
        absent = np.setdiff1d(np.arange(n_v * n_l), grid)
        what = (f"view {int(absent[0]) // n_l}, light {int(absent[0]) % n_l} is missing" if len(absent)
                else "some (view, light) pair appears twice")
        raise ValueError(f"{store.path}: its {store.n_lv} rows are not a full grid of {n_v} views x {n_l} lights "
                         f"({what}); {hint}")
    view_dir = store.view_dir[order].reshape(n_v, n_l, 3)
    off = np.abs(view_dir - view_dir[:, :1]).max(axis=2)
    if (off > VIEW_TOL).any():
        v, l = (int(i) for i in np.unravel_index(int(np.argmax(off)), off.shape))
        raise ValueError(f"{store.path}: row {int(order[v * n_l + l])} (view {v}, light {l}) has another view "
                         f"direction than the view's first row (differs by {float(off[v, l]):.3g}); the rows are not "
                         f"views x lights; {hint}")
    return order, n_v, n_l


def _angles(d: np.ndarray) -> np.ndarray:
    """Unit directions ``(..., 3)`` -> ``(..., 2)`` float32 (theta, phi) radians, phi in [0, 2 pi)."""
    theta = np.arccos(np.clip(d[..., 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(d[..., 1], d[..., 0]), 2 * np.pi)
    return np.stack([theta, phi], axis=-1).astype(np.float32)


def _xml(store: BtfStore, n_v: int, n_l: int, scale: float, basis: str = "") -> str:
    attrs = store.attrs
    escape = str.maketrans({"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;"})
    fields = {"source": os.path.abspath(store.path) if "://" not in store.path else store.path,
              "kind": store.kind, "content_key": store.content_key or "", "units": attrs.get("units") or "",
              "views": n_v, "lights": n_l, "scale": repr(float(scale)), **({"basis": basis} if basis else {})}
    body = " ".join(f'{key}="{str(value).translate(escape)}"' for key, value in fields.items())
    return f"<btf_pipeline_export {body}/>"


def _file_angles(plan: ExportPlan, light: np.ndarray, view: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """``(n_v, 2)`` view and per-view ``(n_l, 2)`` light angles of the file: an imported store's own float32
    angles (``bonn_view_angles``, ``bonn_light_angles``), so that they are written back bit for bit, when they
    are there and still describe the store's rows; else the store's directions converted."""
    group, n_v, n_l = plan.store.group, plan.n_v, plan.n_l
    converted = _angles(view), tuple(_angles(light[v]) for v in range(n_v))
    if "bonn_view_angles" not in group or "bonn_light_angles" not in group:
        return converted
    views, lights = np.asarray(group["bonn_view_angles"][...]), np.asarray(group["bonn_light_angles"][...])
    if views.shape != (n_v, 2) or lights.shape != (n_v, n_l, 2) or \
            np.abs(sph_to_dir(views) - view).max() > VIEW_TOL or np.abs(sph_to_dir(lights) - light).max() > VIEW_TOL:
        return converted
    return views.astype(np.float32), tuple(lights.astype(np.float32))


def header_for(plan: ExportPlan, scale: float = 1.0) -> CommonHeader:
    """The file's common header: the store's directions as (theta, phi) radians per view, the texture size,
    the cosine flag, the channel names, rotations and metadata of an imported store passed through.

    An imported store's ``attrs["bonn"]`` (:mod:`tasks.bonn.import_btf`) gives the meta block (strings,
    ppmm, rgb scale factor, cosine flag, XML, channel names) and the rotations; any other store gets this
    project's: cosine flag set (the stores hold measured radiance, which includes the cosine of the light's
    polar angle), ppmm from ``sample_size_m`` when known, no rotations. The XML is this project's one
    element (:func:`_xml`: source store, kind, content key, units, views, lights and ``scale``, the factor the
    file's values carry) unless an imported store brings its own and ``scale`` is 1.
    """
    store, n_v, n_l = plan.store, plan.n_v, plan.n_l
    h, w = store.texture_shape
    bonn = store.attrs.get("bonn") or {}
    light = store.light_dir[plan.order].reshape(n_v, n_l, 3)
    view = store.view_dir[plan.order].reshape(n_v, n_l, 3)[:, 0]
    size_m = store.attrs.get("sample_size_m")
    ppmm = float(bonn.get("ppmm", w / (1000.0 * float(size_m)) if size_m else 0.0))
    rotations = bonn.get("rotations")
    rotations = np.zeros((0, 3, 3), np.float32) if rotations is None else \
        np.asarray(rotations, dtype=np.float32).reshape(-1, 3, 3)
    names = tuple(bonn.get("channel_names") or ("R", "G", "B"))
    view_angles, light_angles = _file_angles(plan, light, view)
    return make_header(
        view_angles, light_angles, int(w), int(h),
        signature=SIGNATURE_OF[plan.format], channel_names=names if len(names) == 3 else ("R", "G", "B"),
        cosine_flag=bool(bonn.get("cosine_flag", True)), xml=str(bonn.get("xml") if bonn.get("xml") and scale == 1.0 and not plan.basis_name
                else _xml(store, n_v, n_l, scale, plan.basis_name)),
        measurement_setup=str(bonn.get("measurement_setup", "btf-pipeline export")),
        image_sensor=str(bonn.get("image_sensor", "")), light_source=str(bonn.get("light_source", "")), ppmm=ppmm,
        rgb_scale_factor=tuple(float(v) for v in bonn.get("rgb_scale_factor", (1.0, 1.0, 1.0))), rotations=rotations)


def check_export(store_path: str | os.PathLike, out_file: str | os.PathLike, *, format: str,
                 precision: str = "half", colour_model: int = 0, components: int | None = None,
                 compression: int | str = 0, overwrite: bool = False, lines_per_chunk: int = 4,
                 scale: float | str = 1.0, basis: str | os.PathLike | None = None, basis_class: str | None = None,
                 max_bytes: int = MAX_FACTORISE_BYTES) -> ExportPlan:
    """Every check of :func:`export_store` before anything is written (``btf export`` runs it first).

    Raises
    ------
    ValueError
        An unknown format, precision, colour model or compression, a setting the format has no place for,
        ``components`` out of range, a store that is not views x lights, one too large to factorise in memory.
    FileExistsError
        ``out_file`` exists and ``overwrite`` is false.
    FileNotFoundError, BtfStoreError
        No finished btf-texture store at ``store_path``.
    """
    if format not in FORMATS:
        raise ValueError(f"--format {format!r}: give one of {', '.join(FORMATS)}")
    if precision not in PRECISIONS:
        raise ValueError(f"--precision {precision!r}: give one of {', '.join(PRECISIONS)}")
    if int(colour_model) not in COLOUR_MODELS:
        raise UnknownColourModelError(colour_model, "--colour-model")
    if format != "dfmf" and int(colour_model) != 0:
        raise ValueError(f"--colour-model {colour_model}: {format.upper()} stores RGB (colour model 0) only; use "
                         "--format dfmf for another colour model")
    if format == "bdi" and precision != "half":
        raise ValueError("--precision single: BDI stores half floats only; use --format dfmf or fmf for single "
                         "precision")
    code = BDI_COMPRESSIONS.get(compression, compression) if isinstance(compression, str) else compression
    if code not in BDI_COMPRESSIONS.values():
        raise ValueError(f"--compression {compression!r}: give one of {', '.join(BDI_COMPRESSIONS)} (or 0, 1, 2)")
    if format != "bdi" and code != 0:
        raise ValueError(f"--compression {compression}: only BDI files have chunk compression; drop it")
    if not isinstance(lines_per_chunk, int) or lines_per_chunk < 1:
        raise ValueError(f"--lines-per-chunk {lines_per_chunk!r}: give a positive integer")
    factor = None if scale == "auto" else _number(scale)
    if factor is not None and not (np.isfinite(factor) and factor > 0):
        raise ValueError(f"--scale {scale!r}: give a positive number or auto")
    out = Path(out_file)
    if out.is_dir():
        raise IsADirectoryError(f"{out}: a folder; give --out a file name (e.g. {out / 'material.btf'})")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists; give another --out or --overwrite to replace it")
    store = open_btf_store(store_path)
    order, n_v, n_l = views_lights(store)
    h, w = store.texture_shape
    k_max = min(n_v * n_l * (3 if format == "fmf" else 1), h * w)
    U, basis_name = (None, "") if basis is None and basis_class is None else \
        _model_basis(store, order, basis, basis_class, format, int(colour_model))
    if format == "bdi":
        if components is not None:
            raise ValueError(f"--components {components}: BDI stores the textures, not a factorisation; drop it")
        k = 0
    else:
        if U is not None:
            k_max = min(k_max, U.shape[1])
        k = k_max if components is None else int(components)
        if not 1 <= k <= k_max:
            what = ("the basis' vectors, at most min(rows, texels)" if U is not None else
                    f"min(rows, texels) of this {'FMF' if format == 'fmf' else 'per-channel DFMF'} factorisation")
            raise ValueError(f"--components {components}: give 1 to {k_max} ({what})")
        need = store.n_lv * h * w * 3 * 4
        if need > max_bytes:
            raise ValueError(f"{store.path}: {need / 2**20:.0f} MiB of textures; a {format.upper()} export factorises "
                             f"in memory up to {max_bytes / 2**20:.0f} MiB (its peak memory is 5-8 times that); "
                             "export it as --format bdi, which streams the store band by band")
    return ExportPlan(store, out, format, order, n_v, n_l, PRECISIONS[precision], int(colour_model), k, int(code),
                      factor, None if U is None else U[:, :k], basis_name)


def _model_basis(store: BtfStore, order: np.ndarray, model_dir: Any, cls: str | None, format: str,
                 colour_model: int) -> tuple[np.ndarray, str]:
    """``--basis MODEL_DIR --class CLS``: the class' ALS basis of linear RGB (``classes/CLS/als/U``, ``(n_lv, k)``,
    from `btf build-db`) in file row order, checked against the store's rows; and its name for the XML."""
    from tasks.reconstruct import open_model

    if model_dir is None or not cls:
        raise ValueError("--basis MODEL_DIR and --class CLS go together: give both (a `btf build-db` folder and one "
                         "of its classes)")
    if format != "dfmf" or colour_model != 0:
        raise ValueError(f"--basis: a model basis is exported as DFMF in colour model 0 (the ALS basis is of linear "
                         f"RGB, shared by the channels); give --format dfmf without --colour-model, not {format} "
                         f"with colour model {colour_model}")
    group = open_model(model_dir)
    classes = sorted(group["classes"].group_keys()) if "classes" in group else []
    if cls not in classes or "als" not in group[f"classes/{cls}"]:
        raise ValueError(f"{model_dir}: no ALS basis of class {cls!r} (classes: {', '.join(classes) or 'none'}); "
                         "give one of them, or run `btf build-db` with materials of that class")
    ml, mv = np.asarray(group["light_dir"][...]), np.asarray(group["view_dir"][...])
    sl, sv = store.light_dir, store.view_dir
    if ml.shape != sl.shape or not (np.allclose(ml, sl, atol=1e-9) and np.allclose(mv, sv, atol=1e-9)):
        raise ValueError(f"{store.path}: its {len(sl)} light/view pairs are not the rows of the model's bases "
                         f"({len(ml)} pairs, or other directions); export with a model built on this sampling")
    U = np.asarray(group[f"classes/{cls}/als/U"][...], dtype=np.float64)
    return U[order], f"{os.path.abspath(model_dir)}: classes/{cls}/als"


def _number(text: Any) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return float("nan")


def export_store(store_path: str | os.PathLike, out_file: str | os.PathLike, *, format: str,
                 precision: str = "half", colour_model: int = 0, components: int | None = None,
                 compression: int | str = 0, overwrite: bool = False, lines_per_chunk: int = 4,
                 scale: float | str = 1.0, basis: str | os.PathLike | None = None, basis_class: str | None = None,
                 max_bytes: int = MAX_FACTORISE_BYTES) -> dict[str, Any]:
    """Write a finished btf-texture store as a Bonn BTF file.

    Parameters
    ----------
    store_path : path-like
        A finished btf-texture store whose rows form views x lights (:func:`views_lights`).
    out_file : path-like
        The file to write (``<out_file>.partial`` while it is written).
    format : {"dfmf", "fmf", "bdi"}
    precision : {"half", "single"}
        Scalars of the factors (DFMF, FMF); BDI is half only.
    colour_model : int
        DFMF's colour model (:data:`btfcore.bonn.COLOUR_MODELS`); FMF and BDI are RGB (0).
    components : int, optional
        ``K`` of each factorisation; default all (``min(rows, n_tx)``), lossless up to ``precision``.
    compression : {0, 1, 2} or {"raw", "bzip2", "sparse"}
        BDI chunk compression.
    overwrite : bool
        Replace an existing ``out_file``.
    lines_per_chunk : int
        BDI scan lines per chunk.
    scale : float or "auto"
        The file holds the store's values times ``scale`` (recorded in the XML; readers do not undo it).
        ``"auto"``: 1 when the values fit half floats, else the power of two that brings the largest value a
        half float must hold (BDI: a texel value; DFMF/FMF of a linear colour model: a singular value or an
        ``S V^T`` entry) to at most 2^14 (uncorrected stores of `btf ingest` hold DN/s, far beyond 65504).
    basis, basis_class : path-like and str, optional
        Export on a model basis instead of the store's own SVD (DFMF, colour model 0): ``U`` is the class'
        ALS basis of the `btf build-db` folder ``basis`` (its first ``components`` vectors), shared by the
        three channels, and ``S V^T = B_c^T U`` the store projected on it (``S``: the norms of its columns).
        Lossy unless the basis spans the store's rows; the rows must be the model's.
    max_bytes : int
        Largest store (float32 texture bytes) a DFMF or FMF export factorises in memory.

    Returns
    -------
    dict
        ``out``, ``format``, ``signature``, ``bytes`` (file size), ``views``, ``lights``, ``texture_shape``,
        ``precision``, ``colour_model``, ``components`` (per channel), the largest absolute and the relative
        RMS error of the file's values against the store (DFMF and FMF: computed from the factors as written,
        rounded to ``precision``; in store units, the scale divided out), ``scale`` and ``cosine_flag``.

    Raises
    ------
    ValueError, FileExistsError, FileNotFoundError
        As :func:`check_export`; also NaN/Inf in the store, values outside the colour model's domain and
        factor values a half float cannot hold (the message says to use ``--precision single``).
    """
    plan = check_export(store_path, out_file, format=format, precision=precision, colour_model=colour_model,
                        components=components, compression=compression, overwrite=overwrite,
                        lines_per_chunk=lines_per_chunk, scale=scale, basis=basis, basis_class=basis_class,
                        max_bytes=max_bytes)
    header, summary = write_file(plan.out, lambda tmp: _write_bdi(plan, tmp, lines_per_chunk)
                                 if plan.format == "bdi" else _write_factorised(plan, tmp))
    h, w = plan.store.texture_shape
    return {"command": "export", "out": str(plan.out.resolve()), "format": plan.format,
            "signature": header.signature, "bytes": plan.out.stat().st_size, "source": str(store_path),
            "views": plan.n_v, "lights": plan.n_l, "texture_shape": [h, w], "precision": precision,
            "colour_model": plan.colour_model, "cosine_flag": header.cosine_flag,
            "rotations": int(len(header.rotations)), **summary}


# --------------------------------------------------------------------------- factorised formats


def _textures(plan: ExportPlan) -> np.ndarray:
    """The store's textures in file row order, ``(n_lv, n_tx, 3)`` float32; NaN/Inf refused."""
    btf = plan.store.btf
    data = np.asarray(btf[...] if _identity(plan) else btf.get_orthogonal_selection((plan.order,)), dtype=np.float32)
    _refuse_nonfinite(plan, data, 0)
    return data.reshape(len(data), -1, 3)


def _identity(plan: ExportPlan) -> bool:
    return bool(np.array_equal(plan.order, np.arange(len(plan.order))))


def _refuse_nonfinite(plan: ExportPlan, data: np.ndarray, y0: int) -> None:
    """NaN/Inf in ``data`` (file rows x texture rows from ``y0``) refused, naming the store's row and texel."""
    bad = ~np.isfinite(data)
    if bad.any():
        r, y, x, c = (int(v) for v in np.unravel_index(int(np.argmax(bad)), bad.shape))
        raise ValueError(f"{plan.store.path}: btf[{int(plan.order[r])}, {y0 + y}, {x}, {c}] is {data[r, y, x, c]!r}; "
                         "a BTF file cannot hold NaN/Inf: write the store again (the command that made it)")


def _auto_scale(largest: float) -> float:
    """``--scale auto``: 1 when ``largest`` fits a half float with headroom (at most :data:`AUTO_TARGET`), else the
    power of two that brings it into ``(AUTO_TARGET / 2, AUTO_TARGET]`` (exact: only exponents change)."""
    if not largest > AUTO_TARGET:
        return 1.0
    return float(2.0 ** np.floor(np.log2(AUTO_TARGET / largest)))


def _rounded(a: np.ndarray, scalar_size: int, what: str, path: Any) -> np.ndarray:
    """``a`` as the file will hold it (float16 or float32); values a half float cannot hold refused."""
    if scalar_size == 2 and a.size and float(np.abs(a).max()) > HALF_MAX:
        raise ValueError(f"{path}: {what} reaches {float(np.abs(a).max()):.4g}, beyond the largest half float "
                         f"({HALF_MAX:g}); export with --precision single, or --scale auto (the values times a power "
                         "of two, recorded in the XML)")
    return a.astype(np.float16 if scalar_size == 2 else np.float32)


def _row_blocks(n_rows: int, row_bytes: int) -> list[tuple[int, int]]:
    """``[(r0, r1), ...]`` covering ``n_rows`` rows in blocks of about :data:`BLOCK_BYTES`."""
    step = max(1, BLOCK_BYTES // max(1, row_bytes))
    return [(r, min(n_rows, r + step)) for r in range(0, n_rows, step)]


def _encoded(plan: ExportPlan, rgb: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(channels (n_lv, n_tx, 3) float32, mean, matrix)`` of the DFMF colour model, of ``rgb * scale``;
    encoded block of rows by block (one float64 block at a time) except PCA (3), whose mean and matrix depend
    on all texels. Model 0 at scale 1 is ``rgb`` itself (no copy)."""
    path, model = plan.store.path, plan.colour_model
    if model == 0 and scale == 1.0:
        return rgb, np.zeros(3, np.float32), np.eye(3, dtype=np.float32)
    blocks = [(0, len(rgb))] if model == 3 else _row_blocks(len(rgb), rgb[0].nbytes * 2)
    out = np.empty_like(rgb)
    mean, matrix = np.zeros(3, np.float32), np.eye(3, dtype=np.float32)
    for r0, r1 in blocks:
        block = rgb[r0:r1] * np.float32(scale) if scale != 1.0 else rgb[r0:r1]
        try:
            out[r0:r1], mean, matrix = encode_colour(block, model)
        except ValueError as exc:                                         # outside the model's domain
            raise ValueError(f"{path}: {exc}") from None
        if not np.isfinite(out[r0:r1]).all():
            raise ValueError(f"{path}: colour model {model} ({COLOUR_MODELS[model]}) cannot encode this store's "
                             "values (negative radiance, e.g. noise of dark texels, has no logarithm); use "
                             "--colour-model 0 (RGB) or 1 (YUV)")
    return out, mean, matrix


def _factors(plan: ExportPlan, rgb: np.ndarray) -> tuple[list, np.ndarray, np.ndarray, float]:
    """Unrounded float64 ``(S, U, SxV)`` per factorisation (DFMF: per channel of the colour model; FMF: one of
    all channels, rows ``c + 3 * lv``), the colour mean and matrix, and the scale of the file's values.

    One float64 matrix is in memory at a time (the channel being factorised). ``--scale F`` multiplies the
    RGB before encoding; ``auto`` (``plan.scale`` None) scales ``S`` and ``SxV`` of a linear colour model
    (0, 1, 3, 4) afterwards by :func:`_auto_scale` of their largest value (the same as factorising scaled
    data, the mean scaled with them); log models and single precision keep scale 1.
    """
    scale = 1.0 if plan.scale is None else plan.scale
    n_lv, n_tx, _ = rgb.shape
    if plan.format == "fmf":
        B = np.empty((n_lv, 3, n_tx), np.float64)                    # rows c + 3 * lv: channel fastest
        B[...] = rgb.transpose(0, 2, 1)
        if scale != 1.0:
            B *= scale
        factors = [list(factorise(B.reshape(n_lv * 3, n_tx), plan.components))]
        del B
        mean, matrix = np.zeros(3, np.float32), np.eye(3, dtype=np.float32)
    elif plan.basis is not None:                                   # U shared; S V^T = B_c^T U
        U = np.ascontiguousarray(plan.basis)
        factors = []
        for c in range(3):
            SxV = (rgb[..., c].T.astype(np.float64) * scale) @ U
            factors.append([np.linalg.norm(SxV, axis=0), U, SxV])
        mean, matrix = np.zeros(3, np.float32), np.eye(3, dtype=np.float32)
    else:
        channels, mean, matrix = _encoded(plan, rgb, scale)
        factors = [list(factorise(channels[..., c].astype(np.float64), plan.components)) for c in range(3)]
        del channels
    if plan.scale is None and plan.scalar_size == 2 and plan.colour_model in LINEAR_MODELS:
        largest = max(max(float(np.abs(S).max()), float(np.abs(SxV).max())) for S, _, SxV in factors)
        scale = _auto_scale(largest)
        for f in factors:
            f[0], f[2] = f[0] * scale, f[2] * scale
        mean = np.asarray(mean, np.float64) * scale
    return factors, np.asarray(mean, np.float32), np.asarray(matrix, np.float32), scale


def _write_factorised(plan: ExportPlan, partial: Path) -> tuple[CommonHeader, dict[str, Any]]:
    """DFMF (per channel, in the colour model) or FMF (all channels in one) written to ``partial``; the
    file's values decoded again block of rows by block for the error summary."""
    from tasks.bonn.dfmf import write_dfmf, write_fmf

    rgb = _textures(plan)                                              # (n_lv, n_tx, 3)
    n_lv, n_tx, _ = rgb.shape
    factors, mean, matrix, scale = _factors(plan, rgb)
    header = header_for(plan, scale)
    where = "" if plan.format == "fmf" else "channel {c}'s "
    S_, U_, SxV_ = ([_rounded(f[i], plan.scalar_size, where.format(c=c) + name, plan.store.path)
                     for c, f in enumerate(factors)] for i, name in enumerate(("singular value", "U", "S V^T")))
    del factors
    errors = _ErrorSum()
    if plan.format == "fmf":
        group = plan.store.group
        height_map = np.asarray(group["height_map"][...], np.float32) if "height_map" in group else None
        write_fmf(str(partial), header, S_[0], U_[0], SxV_[0], scalar_size=plan.scalar_size, height_map=height_map)
        for r0, r1 in _row_blocks(n_lv, rgb[0].nbytes * 4):
            decoded = decode_textures(U_, SxV_, slice(3 * r0, 3 * r1)).reshape(r1 - r0, 3, n_tx).transpose(0, 2, 1)
            errors.add(decoded, rgb[r0:r1], scale)
    else:
        write_dfmf(str(partial), header, plan.colour_model, mean, matrix, S_, U_, SxV_, scalar_size=plan.scalar_size)
        for r0, r1 in _row_blocks(n_lv, rgb[0].nbytes * 4):
            errors.add(decode_colour(decode_textures(U_, SxV_, slice(r0, r1)), plan.colour_model, mean, matrix),
                       rgb[r0:r1], scale)
    return header, {"components": [int(u.shape[1]) for u in U_], "scale": scale, **errors.result()}


class _ErrorSum:
    """The largest absolute and the relative RMS error of a file's values (scale divided out) against the
    store's, accumulated block by block."""

    def __init__(self) -> None:
        self.d2, self.v2, self.largest = 0.0, 0.0, 0.0

    def add(self, written: np.ndarray, original: np.ndarray, scale: float) -> None:
        diff = written.astype(np.float64) / scale - original
        self.d2 += float(np.sum(diff ** 2))
        self.v2 += float(np.sum(original.astype(np.float64) ** 2))
        self.largest = max(self.largest, float(np.abs(diff).max(initial=0.0)))

    def result(self) -> dict[str, float]:
        return {"max_abs_error": self.largest,
                "relative_rms_error": float(np.sqrt(self.d2 / self.v2)) if self.v2 > 0 else 0.0}


# --------------------------------------------------------------------------- BDI


class _BdiSource:
    """``source(y0, y1)``: the store's textures of scan lines ``y0 .. y1 - 1`` in file row order times the scale,
    ``(n_lv, y1 - y0, w, 3)`` float32, read from the store in bands of about :data:`BDI_READ_BYTES` (whole
    multiples of ``lines_per_chunk``), one band in memory at a time; NaN/Inf and values beyond the half-float
    range refused with the store's row and texel. ``plan.scale`` None (``auto``) reads the store once first
    for its largest value (:func:`_auto_scale`)."""

    def __init__(self, plan: ExportPlan, lines_per_chunk: int) -> None:
        self.plan, self.order, self.identity = plan, plan.order, _identity(plan)
        h, w = plan.store.texture_shape
        per_line = len(plan.order) * w * 3 * 4
        self.lines = max(1, BDI_READ_BYTES // (per_line * lines_per_chunk)) * lines_per_chunk
        self.start, self.band = -1, np.zeros((0, 0), np.float32)
        self.scale = 1.0 if plan.scale is None else plan.scale
        self.errors, self.seen = _ErrorSum(), set()                     # bands counted in errors
        if plan.scale is None:
            largest = 0.0
            for y0 in range(0, h, self.lines):
                band = self._band(y0, min(h, y0 + self.lines))
                largest = max(largest, float(np.abs(band).max(initial=0.0)))
            self.scale = _auto_scale(largest)

    def _band(self, y0: int, y1: int) -> np.ndarray:
        btf = self.plan.store.btf
        band = np.asarray(btf[:, y0:y1] if self.identity else
                          btf.get_orthogonal_selection((self.order, slice(y0, y1))), dtype=np.float32)
        _refuse_nonfinite(self.plan, band, y0)
        return band

    def _read(self, y0: int, y1: int) -> None:
        band = self._band(y0, y1)
        original = band.copy() if self.scale != 1.0 else band
        if self.scale != 1.0:
            band *= np.float32(self.scale)
        if float(np.abs(band).max(initial=0.0)) > HALF_MAX:
            raise ValueError(f"{self.plan.store.path}: texture values reach {float(np.abs(band).max()):.4g}, beyond "
                             f"the largest half float ({HALF_MAX:g}) that BDI stores; export with --scale auto (the "
                             "values times a power of two, recorded in the XML) or as --format dfmf --precision "
                             "single")
        if (y0, y1) not in self.seen:
            self.seen.add((y0, y1))
            self.errors.add(band.astype(np.float16), original, self.scale)
        self.start, self.band = y0, band

    def __call__(self, y0: int, y1: int) -> np.ndarray:
        if self.start < 0 or not self.start <= y0 <= y1 <= self.start + self.band.shape[1]:
            start = y0 - y0 % self.lines
            self._read(start, min(self.plan.store.texture_shape[0], max(y1, start + self.lines)))
        return self.band[:, y0 - self.start:y1 - self.start]


def _write_bdi(plan: ExportPlan, partial: Path, lines_per_chunk: int) -> tuple[CommonHeader, dict[str, Any]]:
    """BDI written band by band from the store to ``partial``."""
    from tasks.bonn.bdi import write_bdi

    source = _BdiSource(plan, lines_per_chunk)
    header = header_for(plan, source.scale)
    group, shape = plan.store.group, plan.store.texture_shape
    mask = np.asarray(group["bonn_mask"][...], dtype=bool) if "bonn_mask" in group else None
    write_bdi(str(partial), header, source, compression=plan.compression, lines_per_chunk=lines_per_chunk,
              mask=mask if mask is not None and mask.shape == shape else None)
    return header, {"components": [], "scale": source.scale, "lines_per_chunk": lines_per_chunk, **source.errors.result(),
                    "compression": {v: k for k, v in BDI_COMPRESSIONS.items()}[plan.compression]}
