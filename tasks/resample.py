"""BTF store -> BTF store on a common light x view sampling (docs/architecture.md, "Stages": resample).

A BTF store written by ``btf ingest`` (``btf-texture``, :mod:`tasks.stores.btf`, rows flattened over
(turntable, camera, light) in the dome's own directions) is resampled to a
target sampling, the Cartesian product of a light set and a view set: the
UBO2014 151 x 151 set (:func:`btfcore.capture.resample.ubo2014_directions`) or a
user's JSON file ``{"light_dirs": [[x, y, z], ...], "view_dirs": [...]}``.

The weights ``W`` ``(n_dst, n_src)`` (:func:`btfcore.capture.resample.resample_weights`,
at most 9 non-zeros per row) are built once in the driver. The output store is
written by one Dask task per group of target views: a task reads only the
source rows its rows of ``W`` use (chunk by chunk, so only the source views it
needs), computes ``B_dst = W B_src`` for its views with one sparse product,
writes each view's chunk and then the view's ``written`` marker. The input
store is never modified; a finished output is replaced (``overwrite``) only
by a complete one, built beside it (:mod:`tasks.staging`). Layout:
docs/btf-store.md, "Resampled stores".
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import scipy.sparse as sp
import zarr

from btfcore.capture.resample import (
    lv_outside_hull,
    lv_product,
    resample,
    resample_weights,
    ubo2014_directions,
    unique_directions,
)
from tasks.compute import run_all
from tasks.faults import kill_point
from tasks.staging import commit_staged, output_refusal, staged_target, staging_path, store_attrs, trash_path
from tasks.stores.btf import (
    RESAMPLED_LV_ORDER,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    BtfStore,
    create_btf_store,
    open_btf_store,
)

#: The built-in target sampling.
UBO2014 = "ubo2014"

#: Memory a resampling task may plan for: its output views plus the source rows it reads.
TASK_BYTES = 512 * 2**20

#: Problems listed in one error message about a sampling file.
MAX_PROBLEMS = 20

_FORMAT_HINT = ('give a JSON object {"light_dirs": [[x, y, z], ...], "view_dirs": [[x, y, z], ...]} of '
                'directions in the sample frame (z = surface normal, z > 0), or "ubo2014"')


@dataclass(frozen=True, eq=False)
class Sampling:
    """A target light x view sampling: every light with every view.

    Parameters
    ----------
    name : str
        ``"ubo2014"`` or the file name of a user's sampling.
    light_dirs : (n_l, 3) ndarray of float64
        Unit light directions, ``z > 0``.
    view_dirs : (n_v, 3) ndarray of float64
        Unit view directions, ``z > 0``.
    """

    name: str
    light_dirs: np.ndarray
    view_dirs: np.ndarray

    @property
    def n_l(self) -> int:
        return len(self.light_dirs)

    @property
    def n_v(self) -> int:
        return len(self.view_dirs)

    def rows(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Light, view and ``(view, light)`` index of every target row, view-major.

        Returns
        -------
        light_dir, view_dir : (n_v * n_l, 3) ndarray of float64
        lv_index : (n_v * n_l, 2) ndarray of int32
            Row ``v * n_l + l`` is ``(v, l)``.
        """
        light, view = lv_product(self.light_dirs, self.view_dirs)
        index = np.stack(np.meshgrid(np.arange(self.n_v), np.arange(self.n_l), indexing="ij"), -1)
        return light, view, index.reshape(-1, 2).astype(np.int32)

    def digest(self) -> str:
        """Hash of the directions (rounded to 1e-12), which is all a resampling depends on."""
        h = hashlib.sha256()
        for dirs in (self.light_dirs, self.view_dirs):
            h.update(np.ascontiguousarray(np.round(dirs, 12) + 0.0).tobytes())
        return h.hexdigest()[:16]


def _directions(value: Any, name: str, problems: list[str]) -> np.ndarray | None:
    """Check one direction list of a sampling file; append every problem (with its index)."""
    if not isinstance(value, list) or not value:
        problems.append(f"{name} must be a non-empty list of [x, y, z] directions, found "
                        f"{type(value).__name__ if not isinstance(value, list) else 'an empty list'}")
        return None
    rows = np.zeros((len(value), 3))
    ok = True
    for i, item in enumerate(value):
        if not (isinstance(item, list) and len(item) == 3
                and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in item)):
            problems.append(f"{name}[{i}] = {json.dumps(item)[:60]} is not a list of three numbers [x, y, z]")
            ok = False
            continue
        v = np.array(item, dtype=np.float64)
        norm = float(np.linalg.norm(v)) if np.isfinite(v).all() else math.nan
        if math.isnan(norm):
            problems.append(f"{name}[{i}] = {item} is not finite (NaN or Infinity)")
        elif norm < 1e-12:
            problems.append(f"{name}[{i}] = {item} is the zero vector, not a direction")
        elif v[2] <= 0.0:
            problems.append(f"{name}[{i}] = {item} points at or below the horizon (z = {v[2]:g} <= 0); "
                            "directions must have z > 0 (z is the surface normal)")
        else:
            rows[i] = v / norm                                    # non-unit vectors are normalised
            continue
        ok = False
    if not ok:
        return None
    unique, inverse = unique_directions(rows)
    if len(unique) < len(rows):
        first = np.full(len(unique), -1)
        for i, u in enumerate(inverse):
            if first[u] < 0:
                first[u] = i
            else:
                problems.append(f"{name}[{i}] repeats {name}[{first[u]}]; each direction must appear once")
        return None
    return rows


def load_sampling(sampling: str | os.PathLike) -> Sampling:
    """The target sampling named by ``--sampling``: ``"ubo2014"`` or a JSON file.

    Parameters
    ----------
    sampling : str or path-like
        ``"ubo2014"`` (151 x 151 directions) or the path of a JSON object
        ``{"light_dirs": [[x, y, z], ...], "view_dirs": [[x, y, z], ...]}``
        in the sample frame; the target rows are every light with every view.

    Returns
    -------
    Sampling
        Non-unit vectors are normalised.

    Raises
    ------
    FileNotFoundError
        When the file does not exist.
    ValueError
        When the file is not such JSON; every problem is listed with its
        array and index (zero vectors, NaN/Infinity, ``z <= 0``, repeated
        directions, entries that are not three numbers).
    """
    if str(sampling) == UBO2014:
        dirs = ubo2014_directions()
        return Sampling(UBO2014, dirs, dirs.copy())
    path = Path(sampling)
    if not path.is_file():
        raise FileNotFoundError(f"sampling file {path} does not exist; {_FORMAT_HINT}")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable JSON sampling file ({exc}); {_FORMAT_HINT}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object, found {type(data).__name__}; {_FORMAT_HINT}")
    problems: list[str] = []
    dirs = {}
    for key in ("light_dirs", "view_dirs"):
        if key not in data:
            problems.append(f"{key} is missing")
        else:
            dirs[key] = _directions(data[key], key, problems)
    if problems:
        listed = problems[:MAX_PROBLEMS] + ([f"... and {len(problems) - MAX_PROBLEMS} more"]
                                            if len(problems) > MAX_PROBLEMS else [])
        raise ValueError(f"{path}: {len(problems)} problem(s) in the sampling file:\n  " + "\n  ".join(listed)
                         + f"\nFix them and run again; {_FORMAT_HINT}")
    return Sampling(path.name, dirs["light_dirs"], dirs["view_dirs"])


# --------------------------------------------------------------------------- stores


def open_source(path: str | os.PathLike) -> BtfStore:
    """Open a finished BTF store for reading (:func:`tasks.stores.btf.open_btf_store`), or say what is
    wrong with it.

    Raises
    ------
    FileNotFoundError
        When nothing is at ``path``.
    ValueError
        When it is not a btf-texture store, is unfinished (``complete`` false) or
        its arrays do not fit together; the message names the path and the fix.
    """
    source = open_btf_store(path, produced_by="`btf ingest`")
    if source.content_key is None:
        raise ValueError(f"{path}: attribute ingest_hash is missing; give a BTF store written by `btf ingest`")
    return source


def resample_hash(source: BtfStore, sampling: Sampling) -> str:
    """What a resampled store depends on: the source's content hash, the target directions, the schema."""
    payload = {"source": source.content_key, "sampling": sampling.digest(),
               "schema": f"{SCHEMA_NAME}/{SCHEMA_VERSION}", "method": "barycentric-parabolic-delaunay"}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]


def _resample_target(out: Path, key: str, overwrite: bool) -> tuple[Path, bool]:
    """The store this resampling writes and whether it is the staging store of a replacement
    (:func:`tasks.staging.staged_target`, keyed by ``resample_hash``); an empty folder at ``out``
    counts as nothing there (it is replaced, as with ``overwrite``)."""
    empty = out.is_dir() and not any(out.iterdir())
    refusal = lambda attrs: output_refusal(out, attrs, "resample_hash", key,  # noqa: E731
                                           "resampled BTF store", "another source or sampling")
    return staged_target(out, "resample_hash", key, overwrite or empty, refusal)


def create_resampled_store(path: str | os.PathLike, source_path: str | os.PathLike, source: BtfStore,
                           sampling: Sampling, key: str, outside_view: np.ndarray,
                           outside_light: np.ndarray) -> BtfStore:
    """Create (replacing whatever is at ``path``) an empty resampled BTF store.

    Parameters
    ----------
    path : path-like
        The new store.
    source_path, source : path-like, BtfStore
        The finished source store (:func:`open_source`).
    sampling : Sampling
        Target directions.
    key : str
        :func:`resample_hash` of source and sampling.
    outside_view, outside_light : (n_v * n_l,) ndarray of bool
        Rows whose target view / light lies outside the measured hull
        (:func:`btfcore.capture.resample.lv_outside_hull`).

    Returns
    -------
    BtfStore
        ``btf`` (zeros), directions, ``lv_index``, target sets, ``outside_hull``,
        ``written`` (zeros) and the attributes, ``complete`` false.
    """
    n_v, n_l = sampling.n_v, sampling.n_l
    h, w = source.texture_shape
    light_dir, view_dir, lv_index = sampling.rows()
    outside = outside_view | outside_light
    attrs = source.attrs
    resampled_from = {"path": str(Path(source_path).resolve()), "ingest_hash": attrs.get("ingest_hash")}
    for source_key in ("resample_hash", "import_hash"):
        if attrs.get(source_key):
            resampled_from[source_key] = attrs[source_key]
    return create_btf_store(path, {
        "units": attrs.get("units"), "lv_order": RESAMPLED_LV_ORDER, "views_lights": [n_v, n_l],
        "sampling": sampling.name, "resampled_from": resampled_from, "resample_hash": key,
        "method": "barycentric interpolation on Delaunay triangulations in the parabolic map, "
                  "per-view light triangulation (btfcore.capture.resample.resample_weights); outside the "
                  "measured hull the nearest hull point's weights",
        "outside_hull": {"rows": int(outside.sum()), "view": int(outside_view.sum()),
                         "light": int(outside_light.sum())},
    }, light_dir=light_dir, view_dir=view_dir, lv_index=lv_index, texture_shape=(h, w), rows_per_chunk=n_l, band=h,
        written_shape=(n_v,), small={"target_light_dirs": sampling.light_dirs, "target_view_dirs": sampling.view_dirs,
                                     "outside_hull": outside})


# --------------------------------------------------------------------------- work


def _raise_nonfinite(buf: np.ndarray, rows: np.ndarray, source_path: str) -> None:
    bad = ~np.isfinite(buf)
    if bad.any():
        i, y, x, ch = (int(v) for v in np.unravel_index(int(np.argmax(bad)), buf.shape))
        raise ValueError(f"{source_path}: btf[{int(rows[i])}, {y}, {x}, {ch}] = {float(buf[i, y, x, ch])!r}; "
                         "the source holds NaN/Inf and cannot be resampled; re-run `btf ingest` into a new --out")


def resample_views(source_path: str, out_path: str, views: Sequence[int], weights: sp.csr_matrix) -> dict[str, Any]:
    """Resample a group of target views and write them (one Dask task).

    Parameters
    ----------
    source_path, out_path : str
        Source BTF store and the resampled store being written.
    views : sequence of int
        Target view indices; each owns output rows ``v * n_l ... (v + 1) * n_l``,
        exactly one chunk of ``btf``.
    weights : (len(views) * n_l, n_src) scipy.sparse.csr_matrix
        The rows of ``W`` of these views, in order.

    Returns
    -------
    dict
        ``views`` written and ``source_chunks`` read.

    Notes
    -----
    Only the source rows with a non-zero weight are read, chunk by chunk
    (a chunk is one source view), into one buffer; ``W`` restricted to those
    columns keeps each row's column order, so the product is the same as the
    in-memory ``resample(B, W)`` of these rows. Each view's marker is set
    after all the group's data is written.
    """
    src = zarr.open_group(source_path, mode="r", zarr_format=3)["btf"]
    out = BtfStore(out_path, "r+").group
    n_l = weights.shape[0] // len(views)
    needed = np.unique(weights.indices)                           # sorted source rows
    step = src.chunks[0]
    blocks = needed // step
    buf = np.empty((len(needed),) + tuple(src.shape[1:]), dtype=np.float32)
    for k in np.unique(blocks):
        lo, hi = np.searchsorted(blocks, [k, k + 1])
        buf[lo:hi] = src[k * step:(k + 1) * step][needed[lo:hi] - k * step]   # whole chunk read
    W = sp.csr_matrix((weights.data, np.searchsorted(needed, weights.indices), weights.indptr),
                      shape=(weights.shape[0], len(needed)))      # columns renumbered, order kept
    try:
        dst = resample(buf, W)                                    # eq. B_dst = W B_src
    except ValueError:
        _raise_nonfinite(buf, needed, source_path)
        raise
    for i, v in enumerate(views):
        out["btf"][v * n_l:(v + 1) * n_l] = dst[i * n_l:(i + 1) * n_l]      # exactly one chunk
    kill_point("chunk-written")
    for v in views:
        out["written"][v] = 1                                     # markers after the data
    return {"views": [int(v) for v in views], "source_chunks": int(len(np.unique(blocks)))}


def _view_groups(W: sp.csr_matrix, views: Sequence[int], n_l: int, row_bytes: int, max_views: int,
                 budget: int = TASK_BYTES) -> list[list[int]]:
    """Consecutive target views per task: at most ``max_views``, and output plus source rows read
    within ``budget`` bytes (neighbouring views share most of their source rows)."""
    groups: list[list[int]] = []
    group: list[int] = []
    union = np.zeros(0, dtype=np.int64)
    for v in views:
        rows = np.unique(W.indices[W.indptr[v * n_l]:W.indptr[(v + 1) * n_l]])
        grown = np.union1d(union, rows)
        if group and (len(group) >= max_views or (len(grown) + (len(group) + 1) * n_l) * row_bytes > budget):
            groups.append(group)
            group, grown = [], rows
        group.append(int(v))
        union = grown
    return groups + ([group] if group else [])


def check_inputs(source_path: str | os.PathLike, out_path: str | os.PathLike,
                 sampling: str | os.PathLike | Sampling, *,
                 overwrite: bool = False) -> tuple[zarr.Group, Sampling, str, Path, bool]:
    """Check a resampling's inputs before any work: the source store, the sampling and ``--out``.

    A commit into ``out_path`` killed between its renames is finished first
    (:func:`tasks.staging.finish_interrupted_commit`).

    Returns
    -------
    source : zarr.Group
        The finished source store.
    sampling : Sampling
    key : str
        :func:`resample_hash` of the two.
    target : Path
        The store to write: ``out_path``, or its staging store
        (:func:`tasks.staging.staging_path`) when this run replaces the output
        there (``overwrite``) or resumes such a replacement.
    staged : bool
        ``target`` is the staging store.

    Raises
    ------
    FileNotFoundError, ValueError
        As :func:`open_source` and :func:`load_sampling`; ValueError when
        ``out_path`` (or its staging or replaced store) is the source itself.
    FileExistsError
        Something else is at ``out_path`` and not ``overwrite``.
    """
    source = open_source(source_path)
    out = Path(out_path)
    src = Path(source_path).resolve()
    if src in {p.resolve() for p in (out, staging_path(out), trash_path(out))}:
        what = ("is the source store" if out.resolve() == src else
                f"would stage its replacement in the source {src.name}")
        raise ValueError(f"--out {out_path} {what}; resampling never modifies its input, choose another --out")
    sampling = sampling if isinstance(sampling, Sampling) else load_sampling(sampling)
    key = resample_hash(source, sampling)
    return (source, sampling, key, *_resample_target(out, key, overwrite))


def resample_store(source_path: str | os.PathLike, out_path: str | os.PathLike, client: Any, *,
                   sampling: str | os.PathLike | Sampling = UBO2014, overwrite: bool = False,
                   progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Resample a finished BTF store to a common sampling on a Dask cluster; resumes unfinished runs.

    Parameters
    ----------
    source_path : path-like
        BTF store from ``btf ingest`` (``complete`` true); never modified.
    out_path : path-like
        The resampled store to write (docs/btf-store.md, "Resampled stores").
    client : distributed.Client
    sampling : {"ubo2014"}, path-like or Sampling
        Target sampling: UBO2014 151 x 151, or a JSON file (:func:`load_sampling`).
    overwrite : bool
        Replace the store at ``out_path`` (of another source or sampling, or this
        one's: it is recomputed), but only once the new one is complete: it is
        built in the staging store ``X.partial.zarr`` beside ``X.zarr``
        (:func:`tasks.staging.staging_path`) and then renamed over the old one
        (:func:`tasks.staging.commit_staged`). A staging store of this resampling
        is resumed, with or without ``overwrite``.
    progress : callable, optional
        ``progress(views_done, views_total)``.

    Returns
    -------
    dict
        ``rows``, ``views``, ``lights``, ``sampling``, ``staged`` (the run went
        through the staging store), ``views_processed``, ``views_skipped``,
        ``tasks``, ``source_chunks_read``, ``outside_hull_rows`` (and by
        kind), ``weights_seconds``, ``seconds``.

    Raises
    ------
    FileNotFoundError, ValueError, FileExistsError
        Bad source store, sampling or ``out_path`` (:func:`check_inputs`).
    """
    start = time.perf_counter()
    source, sampling, key, target, staged = check_inputs(source_path, out_path, sampling, overwrite=overwrite)
    n_v, n_l = sampling.n_v, sampling.n_l
    summary = {"rows": n_v * n_l, "views": n_v, "lights": n_l, "sampling": sampling.name, "staged": staged}
    store = BtfStore(target, "r+") if (store_attrs(target) or {}).get("resample_hash") == key else None
    if store is not None and store.complete:                  # done; a staged one was killed before its commit
        summary.update(_outside_counts(store))
        if staged:
            commit_staged(out_path, "resample")
        return {**summary, "views_processed": 0, "views_skipped": n_v, "tasks": 0,
                "source_chunks_read": 0, "weights_seconds": 0.0, "seconds": round(time.perf_counter() - start, 3)}
    light_dir, view_dir, _ = sampling.rows()
    src_light, src_view = source.light_dir, source.view_dir
    try:
        W = resample_weights(src_light, src_view, light_dir, view_dir)
        outside_view, outside_light = lv_outside_hull(src_light, src_view, light_dir, view_dir)
    except ValueError as exc:       # src_light/src_view are the store's light_dir/view_dir
        raise ValueError(f"{source_path}: {exc} (src_light/src_view: its light_dir/view_dir arrays); "
                         "re-run `btf ingest` into a new --out") from None
    weights_seconds = time.perf_counter() - start
    if store is None:
        store = create_resampled_store(target, source_path, source, sampling, key, outside_view, outside_light)
    pending = [int(v) for v in np.flatnonzero(store.written == 0)]
    row_bytes = int(np.prod(source.btf.shape[1:])) * 4
    slots = max(1, sum(client.nthreads().values()))
    groups = _view_groups(W, pending, n_l, row_bytes, max_views=max(1, math.ceil(len(pending) / (4 * slots))))
    results = run_all(client, resample_views, [(str(source_path), str(target), views,
                                                W[(np.asarray(views)[:, None] * n_l + np.arange(n_l)).ravel()])
                                               for views in groups], progress, weights=[len(v) for v in groups])
    chunks_read = sum(result["source_chunks"] for result in results)
    store.mark_complete("views")
    summary.update(_outside_counts(store))
    if staged:
        commit_staged(out_path, "resample")
    return {**summary, "views_processed": len(pending),
            "views_skipped": n_v - len(pending), "tasks": len(groups), "source_chunks_read": chunks_read,
            "weights_seconds": round(weights_seconds, 3), "seconds": round(time.perf_counter() - start, 3)}


def _outside_counts(store: BtfStore) -> dict[str, int]:
    counts = store.attrs["outside_hull"]
    return {"outside_hull_rows": counts["rows"], "outside_view_hull_rows": counts["view"],
            "outside_light_hull_rows": counts["light"]}
