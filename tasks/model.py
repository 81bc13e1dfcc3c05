"""The model database (stage 8): per-material bases, class and global merges, ABTF bases.

`btf build-db DB --out MODEL` reads the ingested BTF stores of a database
(``btf-texture``, one per material) and writes one Zarr v3 group,
``MODEL/model.zarr`` (schema ``btf-model`` 1.0):

* ``light_dir``, ``view_dir`` ``(n_lv, 3)``: the common light/view sampling;
* ``materials/<id>/<basis>/{U, sigma}``: per-material bases;
* ``classes/<class>/<basis>/{U, sigma}``: merged per class (eigenspace merging);
* ``global/<basis>/{U, sigma}``: the class models merged;

with ``basis`` one of

* ``log_y``, ``u_y``, ``v_y``: the colour channels of paper 1 §3.1
  (:func:`btfcore.model.colour.to_log_yuv`), ABRDF columns (one per texel);
* ``abtf_log_y``: ``p x p`` ABTF patches of ``log_y`` (paper 1 §3.3),
  non-overlapping for fitting; per material and per class only, as in the thesis;
* ``als``: relative-error weighted basis of the linear RGB BTF by
  alternating least squares (paper 4 eqs. 5-9), merged by eq. (9).

Every basis group carries ``key`` (a hash of its inputs and settings) written
after its arrays: a rerun skips a basis whose key is unchanged, so a killed
build resumes and adding a material recomputes only that material, its
class and the global merge.

Matrices stream through btfcore in texel bands (the BTF store's chunks are
one view x a band of rows), so neither a basis nor an evaluation holds a
material whole: their working memory is a band plus a budget derived from
the worker's memory limit (:func:`work_budget`).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from btfcore.model._lowrank import RankError, TruncatedSVD
from btfcore.model.abtf import blend_patches, patch_matrix, patch_rows
from btfcore.model.als import als_basis
from btfcore.model.colour import to_log_yuv
from btfcore.model.eigenspace_merging import merge_eigenspaces
from btfcore.model.truncated_svd import truncated_svd
from tasks.buffers import prefaulted
from tasks.compute import run_all
from tasks.faults import kill_point
from tasks.integrity import create_array, read_chunk_rows
from tasks.staging import (
    begin_store,
    commit_staged,
    finish_interrupted_commit,
    finish_store,
    seed_staging,
    staging_path,
    store_attrs,
)
from tasks.stores import to_json_attr
from tasks.stores.btf import SCHEMA_NAME as BTF_SCHEMA_NAME
from tasks.stores.common import json_key

SCHEMA_NAME = "btf-model"
SCHEMA_VERSION = "1.0"
#: Bases fitted per material and merged per class and globally (``abtf_log_y`` per class only).
CHANNELS = ("log_y", "u_y", "v_y")
BASES = CHANNELS + ("abtf_log_y", "als")
#: A further basis ``btf build-db`` does not fit, but the acquisition evaluation does: the plain truncated
#: SVD of the linear RGB BTF, the de-noising basis of VMV §4.1 (``D ~ U Sigma V^T``).
LINEAR_SVD = "rgb_svd"


@dataclass(frozen=True)
class ModelSettings:
    """What a model database depends on besides its materials.

    ``None`` for a ``k`` means the thesis' value (paper 1 §4.1: 200 for log Y,
    100 for U/Y and V/Y per material, 2048 merged; 64 components for the
    ALS basis) capped to what the data allows: half the smaller side of a
    material's matrix (a per-material basis is a compression, and the rest
    of its spectrum is noise) and its numerical rank. An explicit
    per-material value larger than that is an error. The merged ``k_class``
    and ``k_global`` are upper bounds for every basis: a merge keeps at most
    that many vectors, and no more than it has or than their rank.
    """

    k_material: dict[str, int | None] = field(default_factory=lambda: {
        "log_y": None, "u_y": None, "v_y": None, "abtf_log_y": None, "als": None})
    k_class: int | None = None
    k_global: int | None = None
    patch: int = 3
    method: str = "auto"
    memory_bytes: int = 1 << 30
    als_iterations: int = 30
    seed: int = 0

    def key(self) -> str:
        return json_key(asdict(self))


THESIS_K = {"log_y": 200, "u_y": 100, "v_y": 100, "abtf_log_y": 200, "als": 64, LINEAR_SVD: 64, "merged": 2048}


def _choose_k(requested: int | None, default: int, limit: int, what: str) -> int:
    """``requested`` (checked against ``limit``) or the thesis ``default`` capped to ``limit``."""
    if requested is None:
        return int(min(default, limit))
    if requested > limit:
        raise ValueError(f"k = {requested} for {what} exceeds what the data allows ({limit}); choose k <= {limit}")
    return int(requested)


# --------------------------------------------------------------------------- the database


@dataclass(frozen=True)
class Material:
    """One ingested BTF store of the database."""

    material_id: str
    cls: str
    path: str
    ingest_hash: str
    n_lv: int
    texture_shape: tuple[int, int]
    rows_id: str


def rows_fingerprint(light_dir: np.ndarray, view_dir: np.ndarray) -> str:
    """Hash of a light/view sampling (directions rounded to 1e-9): equal samplings, equal ids."""
    rounded = np.round(np.concatenate([light_dir, view_dir], axis=1), 9) + 0.0
    return hashlib.sha256(rounded.astype(np.float64).tobytes()).hexdigest()[:16]


def discover(db: str | os.PathLike, class_map: dict[str, str] | None = None,
             min_per_class: int = 2) -> list[Material]:
    """The materials of a database folder: every finished ``btf-texture`` store in it.

    Every problem is collected and raised together (ValueError): stores that
    are unfinished or resampled, materials without a class, a light/view
    sampling that differs from the first store's (the first differing row),
    and classes with fewer than ``min_per_class`` materials (leave-one-out
    needs another material of the class).
    """
    db = Path(db)
    stores = sorted(p for p in db.glob("*.zarr") if p.is_dir())
    problems, found = [], []
    reference = None
    for path in stores:
        try:
            group = zarr.open_group(str(path), mode="r", zarr_format=3)
        except Exception as exc:  # noqa: BLE001 - any unreadable store is reported, not raised
            problems.append(f"{path}: not a readable Zarr group ({exc})")
            continue
        attrs = dict(group.attrs)
        if attrs.get("schema") != BTF_SCHEMA_NAME or "resampled_from" in attrs:
            continue                                             # other stores may share the folder
        if not attrs.get("complete"):
            problems.append(f"{path}: the ingest is unfinished (complete = false); run `btf ingest` again")
            continue
        material = attrs.get("material") or {}
        cls = (class_map or {}).get(path.stem) or (class_map or {}).get(material.get("material_id", "")) \
            or material.get("class")
        if not cls:
            problems.append(f"{path}: no material class (a real capture); give it in --classes FILE.json as "
                            f'{{"{path.stem}": "leather", ...}}')
            continue
        light, view = group["light_dir"][...], group["view_dir"][...]
        if reference is None:
            reference = (path, light, view)
        elif light.shape != reference[1].shape or not (np.allclose(light, reference[1], atol=1e-9)
                                                       and np.allclose(view, reference[2], atol=1e-9)):
            if light.shape != reference[1].shape:
                where = f"{light.shape[0]} light/view pairs, {reference[0].name} {reference[1].shape[0]}"
            else:
                bad = np.flatnonzero(~(np.isclose(light, reference[1], atol=1e-9).all(1)
                                       & np.isclose(view, reference[2], atol=1e-9).all(1)))
                where = f"light_dir/view_dir[{int(bad[0])}] differ from {reference[0].name}'s"
            problems.append(f"{path}: another light/view sampling ({where}); resample both to one sampling "
                            "(btf resample) before building a database")
            continue
        key = attrs.get("ingest_hash") or attrs.get("import_hash")      # ingested, or imported (btf import-btf)
        found.append(Material(material.get("material_id") or path.stem, str(cls), str(path), key,
                              int(light.shape[0]), tuple(attrs["texture_shape"]), rows_fingerprint(light, view)))
    paths: dict[str, list[str]] = {}
    for m in found:                  # the id names its bases in model.zarr and its leave-one-out merges
        paths.setdefault(m.material_id, []).append(Path(m.path).name)
    for mid, names in sorted(paths.items()):
        if len(names) > 1:
            problems.append(f"material_id {mid!r} is shared by {len(names)} stores ({', '.join(names)}): each material "
                            "needs its own id (the stores are copies, or were simulated or ingested with the same "
                            "name); keep one, or give each store its own file name and material id")
    counts: dict[str, list[str]] = {}
    for m in found:
        counts.setdefault(m.cls, []).append(m.material_id)
    for cls, ids in sorted(counts.items()):
        if len(ids) < min_per_class:
            problems.append(f"class {cls!r} has {len(ids)} material ({', '.join(ids)}): each class needs at least "
                            f"{min_per_class} (its basis is tested on a material left out); add materials or "
                            "merge classes with --classes")
    if not found and not problems:
        problems.append(f"{db}: no finished BTF store (btf-texture, from `btf ingest`) in this folder")
    if problems:
        raise ValueError(f"{db}: {len(problems)} problem(s) with the database:\n  " + "\n  ".join(problems))
    return found


# --------------------------------------------------------------------------- streaming a material


def _bands(btf: zarr.Array, multiple: int = 1, max_bytes: int | None = None) -> list[tuple[int, int]]:
    """Row bands of the texture that follow the store's chunks, each a multiple of ``multiple`` rows
    (the last ``h % multiple`` rows, which fill no patch of a non-overlapping tiling, are left out).

    With ``max_bytes``, a chunk's band larger than that (as float32 across all light/view pairs) is
    split into sub-bands that fit (at least ``multiple`` rows): each chunk is then read once per
    sub-band, trading reads for memory when a band across every view is too large for a worker.
    """
    n_lv, h = btf.shape[:2]
    usable = h - h % multiple
    step = max(multiple, btf.chunks[1] // multiple * multiple)
    sub = step
    if max_bytes is not None:
        row_bytes = 4 * n_lv * int(np.prod(btf.shape[2:]))
        sub = min(step, max(multiple, max_bytes // row_bytes // multiple * multiple))
    return [(s, min(s + sub, r + step, usable)) for r in range(0, usable, step)
            for s in range(r, min(r + step, usable), sub)]


def blocks(path: str, basis: str, patch: int = 3, max_bytes: int | None = None, *, transient: bool = False
           ) -> Callable[[], Iterator[np.ndarray]]:
    """A re-iterable source of ``(rows, m_j)`` column blocks of one basis' matrix of a material,
    one block per texel band (:func:`_bands`; ``max_bytes`` bounds a band's float32 bytes).

    ``log_y``/``u_y``/``v_y``: one column per texel of that channel of
    :func:`btfcore.model.colour.to_log_yuv`; ``abtf_log_y``: non-overlapping
    ``patch x patch`` patches of ``log_y`` (:func:`btfcore.model.abtf.patch_matrix`);
    ``als`` and ``rgb_svd``: linear RGB, one column per texel and channel.

    When the whole matrix fits in ``max_bytes`` its blocks are read and
    converted once and kept for every later pass (a small material: the
    passes of a fit would otherwise each re-read and re-convert it).

    ``transient=True`` (a consumer that is done with a block when it asks for the next, as the fits
    are): the bands of ``als`` and ``rgb_svd`` are read into two buffers the source keeps and reuses
    (one where only one band fits ``max_bytes``), so a yielded block is valid only until the next one
    is requested, and may be changed in place. A freshly allocated band costs its page faults on every
    read: 0.9-1.4 s against 0.25 s into a reused buffer for a 522 MB band (docs/benchmarks.md,
    2026-12-05). The other bases' blocks are converted into new arrays either way.
    """
    btf = zarr.open_group(path, mode="r", zarr_format=3)["btf"]
    n_lv = btf.shape[0]
    multiple = patch if basis == "abtf_log_y" else 1
    kept: list[np.ndarray] = []
    linear = basis in ("als", LINEAR_SVD)
    keep = max_bytes is not None and 4 * n_lv * int(np.prod(btf.shape[1:])) // (1 if linear else 3) <= max_bytes
    bands = _bands(btf, multiple, max_bytes)
    row_size = n_lv * int(np.prod(btf.shape[2:]))
    slots: list[np.ndarray] = []                                # reused band buffers (transient only)

    def cached() -> Iterator[np.ndarray]:
        if not kept:
            kept.extend(read(reuse=False))
        yield from kept

    def band(r0: int, r1: int, slot: int | None) -> np.ndarray:
        if slot is None:
            return np.asarray(btf[:, r0:r1])                                  # (n_lv, rows, w, 3)
        if not slots:                                   # one per band in flight: two when reading ahead
            slots.extend(prefaulted(row_size * max(b1 - b0 for b0, b1 in bands), btf.dtype) for _ in range(n_slots))
        out = slots[slot][:row_size * (r1 - r0)].reshape(n_lv, r1 - r0, *btf.shape[2:])
        read_chunk_rows(btf, r0, r1, out)
        return out

    def block(r0: int, r1: int, slot: int | None) -> np.ndarray:
        raw = band(r0, r1, slot)
        if linear:
            return raw.reshape(n_lv, -1)
        x = to_log_yuv(raw)
        if basis == "abtf_log_y":
            return patch_matrix(x[..., 0], patch, overlap=False)
        return np.ascontiguousarray(x[..., CHANNELS.index(basis)].reshape(n_lv, -1))

    # read (and convert) the next band while the caller computes on this one, where two bands fit
    band_bytes = 4 * n_lv * max((r1 - r0 for r0, r1 in bands), default=0) * int(np.prod(btf.shape[2:]))
    ahead = max_bytes is None or 2 * band_bytes <= max_bytes
    n_slots = 2 if ahead else 1

    def read(reuse: bool = transient) -> Iterator[np.ndarray]:
        # only a linear band is the block itself; another basis' block is converted into new arrays, and
        # a kept raw band would add to the memory its conversion takes
        slot = (lambda i: i % n_slots) if reuse and linear else (lambda i: None)
        if not ahead:
            yield from (block(r0, r1, slot(i)) for i, (r0, r1) in enumerate(bands))
            return
        with ThreadPoolExecutor(1, thread_name_prefix="btf-read-ahead") as pool:
            pending = pool.submit(block, *bands[0], slot(0)) if bands else None
            for i in range(len(bands)):
                current = pending.result()
                pending = pool.submit(block, *bands[i + 1], slot(i + 1)) if i + 1 < len(bands) else None
                yield current

    return cached if keep else read


def _n_columns(material: Material, basis: str, patch: int) -> int:
    h, w = material.texture_shape
    if basis == "abtf_log_y":
        return (h // patch) * (w // patch)
    return h * w * (3 if basis in ("als", LINEAR_SVD) else 1)


# --------------------------------------------------------------------------- the store


def check_model_target(path: str | os.PathLike, materials: Sequence[Material]) -> bool:
    """Whether ``path`` holds a model store that a build of ``materials`` adds to (``False``: nothing there).

    Raises
    ------
    FileExistsError
        ``path`` holds something else, or a model store of another light/view sampling.
    """
    from tasks.staging import store_attrs

    attrs = store_attrs(path)
    if attrs is None:
        return False
    if attrs.get("schema") != SCHEMA_NAME:
        raise FileExistsError(f"{path} holds something other than a model store; choose another --out or pass "
                              "--overwrite (the new store is then built beside it and replaces it once complete)")
    if attrs.get("rows_id") != materials[0].rows_id:
        raise FileExistsError(f"{path} holds a model store of another light/view sampling (rows_id "
                              f"{attrs.get('rows_id')!r}, this database {materials[0].rows_id!r}); choose another "
                              "--out or pass --overwrite (the new store is then built beside it and replaces it once "
                              "complete)")
    return True


def read_class_map(path: str | os.PathLike | None) -> dict[str, str] | None:
    """The ``--classes`` JSON of ``btf build-db`` (``{"<store name>": "<class>", ...}``); ``None`` for no file.

    Raises
    ------
    ValueError
        Not readable JSON, or not a mapping of names to class names.
    """
    if not path:
        return None
    try:
        class_map = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable JSON class map ({exc}); write "
                         '{"<store name>": "<class>", ...}') from None
    if not isinstance(class_map, dict) or not all(isinstance(v, str) for v in class_map.values()):
        raise ValueError(f'{path}: expected a JSON object {{"<store name>": "<class>", ...}}')
    return class_map


def open_model_store(path: str | os.PathLike, materials: Sequence[Material]) -> zarr.Group:
    """Create the model store (``complete`` false until :func:`build_database` ends), or reopen it when its
    light/view sampling matches (then it is added to)."""
    first = materials[0]
    src = zarr.open_group(first.path, mode="r", zarr_format=3)
    if check_model_target(path, materials):
        return zarr.open_group(str(path), mode="r+", zarr_format=3)
    group = begin_store(path)
    for name in ("light_dir", "view_dir"):
        data = src[name][...]
        create_array(group, name, shape=data.shape, dtype=data.dtype, chunks=data.shape, compressors=None)[...] = data
    group.attrs.put(to_json_attr({"schema": SCHEMA_NAME, "schema_version": SCHEMA_VERSION, "rows_id": first.rows_id,
                                  "n_lv": first.n_lv, "bases": list(BASES), "complete": False}))
    return finish_store(path, group)


def model_target(path: str | os.PathLike, materials: Sequence[Material], overwrite: bool = False
                 ) -> tuple[Path, bool]:
    """The store a build of ``materials`` writes for ``path`` (``OUT/model.zarr``), and whether it is the
    staging store of a replacement (put in place by :func:`tasks.staging.commit_staged` once complete).

    An interrupted commit is finished first. A killed replacement's staging store (``model.partial.zarr``)
    of this sampling resumes. A complete model store of this sampling is not changed in place: the build
    works on a staging copy made of hard links to its files (:func:`tasks.staging.seed_staging`; its keyed
    bases are reused), so that readers and a failed run never see a half-updated database. A new or
    unfinished store (``complete`` false) is written in place. With ``overwrite``, a store of another
    sampling or something else at ``path`` (or beside it, staged) is replaced by a new store built beside it.

    Raises
    ------
    FileExistsError
        ``path`` (or its staging store) holds something other than a model store of this sampling and not
        ``overwrite``.
    """
    path = Path(path)
    finish_interrupted_commit(path)
    staging = staging_path(path)
    if store_attrs(staging) is not None:
        try:
            check_model_target(staging, materials)
            return staging, True
        except FileExistsError:
            if not overwrite:
                raise
            shutil.rmtree(staging)
    attrs = store_attrs(path)
    if attrs is None:
        return path, False
    try:
        check_model_target(path, materials)
    except FileExistsError:
        if not overwrite:
            raise
        return staging, True                         # a new store beside what is there
    if attrs.get("complete") is False:
        return path, False
    seed_staging(path)
    zarr.open_group(str(staging), mode="r+", zarr_format=3).attrs["complete"] = False
    return staging, True


def write_basis(group: zarr.Group, where: str, model: TruncatedSVD, key: str, **attrs: Any) -> None:
    """Write ``U`` and ``sigma`` under ``where`` and then its ``key`` (the resume marker)."""
    sub = group.require_group(where)
    for name, data in (("U", model.U), ("sigma", model.sigma)):
        create_array(sub, name, shape=data.shape, dtype="float64", chunks=data.shape, compressors=None,
                         overwrite=True)[...] = data
    kill_point("chunk-written")
    sub.attrs.put(to_json_attr({"method": model.method, "settings": model.settings, "norm_sq": model.norm_sq,
                                "iterations": model.iterations, "converged": bool(model.converged),
                                "energy_captured": model.energy_captured, **attrs, "key": key}))


def read_basis(group: zarr.Group, where: str) -> TruncatedSVD:
    sub = group[where]
    attrs = dict(sub.attrs)
    return TruncatedSVD(np.asarray(sub["U"][...]), np.asarray(sub["sigma"][...]), attrs.get("method", "stored"),
                        attrs.get("settings", {}), int(attrs.get("iterations", 0)), 0.0,
                        bool(attrs.get("converged", True)), float(attrs.get("norm_sq", 0.0)),
                        group.attrs.get("rows_id"))


def stored_key(group: zarr.Group, where: str) -> str | None:
    try:
        return group[where].attrs.get("key")
    except KeyError:
        return None


# --------------------------------------------------------------------------- per-material bases


def material_key(material: Material, basis: str, settings: ModelSettings) -> str:
    return json_key({"ingest_hash": material.ingest_hash, "basis": basis, "settings": settings.key()})


def fit_material(model_path: str, material: Material, settings: ModelSettings,
                 bases: Sequence[str] = BASES) -> dict[str, Any]:
    """Fit ``bases`` of one material (skipping those already stored with the same key)."""
    group = zarr.open_group(model_path, mode="r+", zarr_format=3)
    done = {}
    for basis in bases:
        where = f"materials/{material.material_id}/{basis}"
        key = material_key(material, basis, settings)
        if stored_key(group, where) == key:
            done[basis] = "reused"
            continue
        try:
            model = _fit_basis(material, basis, settings)
        except ValueError as exc:             # NaN in the BTF, k above the rank: name the store and basis
            message = str(exc)
            raise ValueError(message if message.startswith(material.path) else
                             f"{material.path}: {basis} basis: {message}") from None
        write_basis(group, where, model, key, material=material.material_id, cls=material.cls, basis=basis)
        done[basis] = model.method
    return {"material": material.material_id, "bases": done}


def _fit_basis(material: Material, basis: str, settings: ModelSettings) -> TruncatedSVD:
    rows = material.n_lv * (settings.patch ** 2 if basis == "abtf_log_y" else 1)
    cols = _n_columns(material, basis, settings.patch)
    k = _choose_k(settings.k_material.get(basis), THESIS_K[basis], min(rows, cols) // 2,
                  f"{material.material_id} {basis} ({rows} x {cols})")
    if basis == "als":
        return _fit_als(material, k, settings)

    def fit(k: int) -> TruncatedSVD:
        return truncated_svd(blocks(material.path, basis, settings.patch, band_budget(settings), transient=True),
                             rows, k,
                             settings.method,
                             memory_bytes=settings.memory_bytes, seed=settings.seed,
                             rows_id=f"{material.rows_id}/{basis}")

    return _up_to_rank(fit, k, settings.k_material.get(basis) is None, f"{material.path}: {basis}")


def _up_to_rank(fit: Callable[[int], TruncatedSVD], k: int, chosen: bool, what: str) -> TruncatedSVD:
    """``fit(k)``; when ``k`` was a default (``chosen``) above the data's numerical rank, ``fit(rank)``.
    A ``k`` the user gave above the rank is an error naming ``what``."""
    try:
        return fit(k)
    except RankError as exc:
        if chosen and exc.rank >= 1:
            return fit(exc.rank)
        raise ValueError(f"{what}: {exc}") from None


#: Fraction of the memory one task may use that a solve's working arrays get: the rest holds the band being
#: read, its float32 copy, torch's runtime and the allocator's slack (measured: docs/benchmarks.md, out of core).
WORK_FRACTION = 16


def work_budget(memory_bytes: int) -> int:
    """Working-memory budget of one batched solve: ``1/WORK_FRACTION`` of the smaller of ``memory_bytes``
    and the memory limit of the Dask worker running the task (when there is one)."""
    try:
        from distributed import get_worker
        limit = get_worker().memory_manager.memory_limit or memory_bytes
    except (ImportError, ValueError, AttributeError):
        limit = memory_bytes
    return max(1 << 20, int(min(limit, memory_bytes)) // WORK_FRACTION)


def band_budget(settings: ModelSettings) -> int:
    """Most float32 bytes of one texel band a fit reads at a time: half its working budget (a band
    spans every view, so on a large dome one store chunk's band would not fit a small worker)."""
    return work_budget(settings.memory_bytes) // 2


def _fit_als(material: Material, c: int, settings: ModelSettings) -> TruncatedSVD:
    """The relative-error ALS basis (paper 4 eqs. 5-8) of a material's linear RGB BTF, streamed in texel
    bands (:func:`btfcore.model.als.als_basis` on a block source): one pass estimates the weight floor, then
    one pass per iteration; ``norm_sq`` is accumulated by btfcore in the first of them."""
    bands = blocks(material.path, "als", max_bytes=band_budget(settings), transient=True)

    def clipped() -> Iterator[np.ndarray]:
        for band in bands():                    # radiance: noise below 0 carries no signal (in the reused buffer)
            yield np.maximum(band, 0.0, out=band) if band.dtype == np.float32 else \
                np.maximum(band, 0.0).astype(np.float32)

    res = als_basis(clipped, c, n_iter=settings.als_iterations, seed=settings.seed,
                    chunk_bytes=work_budget(settings.memory_bytes))
    objective = [float(v) for v in res.objective]
    return TruncatedSVD(np.asarray(res.U, np.float64), np.asarray(res.sigma, np.float64), "als",
                        {"c": int(c), "iterations": int(res.iterations), "objective": objective,
                         "floor": res.floor, "backend": res.backend}, int(res.iterations), 0.0,
                        bool(res.converged), res.norm_sq, f"{material.rows_id}/als")


# --------------------------------------------------------------------------- merges


def merge_key(keys: Sequence[str], k: int) -> str:
    return json_key({"members": sorted(keys), "k": k})


def merge_bases(group: zarr.Group, materials: Sequence[Material], settings: ModelSettings,
                exclude: str | None = None, store: bool = True,
                bases: Sequence[str] = BASES, classes: Sequence[str] | None = None
                ) -> dict[str, dict[str, TruncatedSVD]]:
    """Per-class and global merges of ``bases`` (``abtf_log_y``: per class only).

    With ``exclude`` (a material id) the merges leave that material out and
    are returned, not stored: the leave-one-out bases of the evaluation,
    which needs only the bases it projects on. With ``classes`` only those
    classes are merged and the global merge, which needs every class, is
    skipped.
    """
    out: dict[str, dict[str, TruncatedSVD]] = {}
    every = classes is None
    classes = sorted({m.cls for m in materials}) if every else list(classes)
    for basis in bases:
        per_class: dict[str, tuple[TruncatedSVD, str]] = {}
        for cls in classes:
            members = [f"materials/{m.material_id}/{basis}" for m in materials
                       if m.cls == cls and m.material_id != exclude]
            per_class[cls] = _merged(group, f"classes/{cls}/{basis}", members, settings.k_class, store)
        out[basis] = {cls: model for cls, (model, _) in per_class.items()}
        if every and basis != "abtf_log_y":      # per class first, then the class models globally (paper 1 §4.1.1)
            out[basis]["__global__"] = _merged(group, f"global/{basis}", list(per_class.values()),
                                               settings.k_global, store, [f"classes/{c}/{basis}" for c in per_class])[0]
    return out


def _merged(group: zarr.Group, where: str, members: Sequence[str | tuple[TruncatedSVD, str]], k: int | None,
            store: bool, names: Sequence[str] | None = None) -> tuple[TruncatedSVD, str]:
    """Merge stored bases (paths) or given ``(model, key)`` pairs into ``where``; ``(model, key)``."""
    pairs = [(read_basis(group, m), stored_key(group, m)) if isinstance(m, str) else m for m in members]
    models = [model for model, _ in pairs]
    available = min(sum(m.k for m in models), models[0].U.shape[0])
    # a merged k is an upper bound: one value serves every basis (the chroma bases have few vectors and
    # low rank), and the leave-one-out merges have fewer vectors to merge
    k = min(k or THESIS_K["merged"], available)
    key = merge_key([key for _, key in pairs], k)
    if store and stored_key(group, where) == key:
        return read_basis(group, where), key
    # one merged k serves every basis, and the chroma bases have low rank: a merge keeps at most k
    merged = _up_to_rank(lambda k: merge_eigenspaces(models, k), k, True, where)
    if store:
        write_basis(group, where, merged, key, members=list(names or members))
    return merged, key


# --------------------------------------------------------------------------- evaluation


def projection_errors(path: str, U: np.ndarray, basis: str = "log_y", patch: int = 3,
                      max_bytes: int | None = None) -> np.ndarray:
    """Relative projection error of a material's matrix onto the first k columns of ``U``, for every k.

    :math:`\\varepsilon_k = \\|U_k U_k^T B - B\\|_F / \\|B\\|_F` (paper 1 §4.1.1), from one
    streaming pass: :math:`\\varepsilon_k^2 = 1 - \\sum_{i<k} \\|u_i^T B\\|^2 / \\|B\\|_F^2`
    for orthonormal ``U``.

    Returns
    -------
    (k_max,) ndarray: entry ``k - 1`` is :math:`\\varepsilon_k`.
    """
    total, captured = 0.0, np.zeros(U.shape[1])
    for block in blocks(path, basis, patch, max_bytes, transient=True)():
        b = block.astype(np.float64)
        total += float(np.sum(b * b))
        captured += np.sum((U.T @ b) ** 2, axis=1)
    return np.sqrt(np.maximum(1.0 - np.cumsum(captured) / total, 0.0))                  # eq. epsilon


def _eval_ks(k_max: int) -> list[int]:
    """The basis sizes an ABTF evaluation reports: 1, 2, 4, ... and ``k_max``."""
    return sorted({2 ** i for i in range(k_max.bit_length()) if 2 ** i <= k_max} | {k_max})


def abtf_projection_errors(path: str, U: np.ndarray, patch: int, budget_bytes: int) -> list[float | None]:
    """Relative log Y error of a material's texels after projecting ALL its ``patch x patch`` patches
    on an ABTF basis and blending them back, every patch weighted equally (paper 1 §4.1.2).

    Computed for k = 1, 2, 4, ... and the basis size; entry ``k - 1`` of the list, ``None``
    elsewhere. Streams the material in texture-row bands, each read with the ``patch - 1`` rows
    of halo on either side that the patches covering its rows need, and projects a band's
    patches in slices of at most ``budget_bytes`` of float64 columns: each texel is blended from
    every patch that covers it, so the result equals projecting the whole texture at once.
    """
    btf = zarr.open_group(path, mode="r", zarr_format=3)["btf"]
    n_lv, h, w = btf.shape[:3]
    ks = _eval_ks(U.shape[1])
    sq_err, sq_norm = np.zeros(len(ks)), 0.0
    step = max(1, budget_bytes // (patch * patch * n_lv * max(w - patch + 1, 1) * 8))   # texel rows a slice

    def covering(t0: int, t1: int) -> tuple[int, int]:
        """The patch rows whose patches cover texel rows t0:t1 (patch row i covers rows i:i + patch)."""
        return max(0, t0 - patch + 1), min(t1, h - patch + 1)

    for r0, r1 in _bands(btf, 1, budget_bytes // 2):
        lo = covering(r0, r1)[0]
        log_y = to_log_yuv(np.asarray(btf[:, lo:min(h, r1 + patch - 1)]))[..., 0].astype(np.float64)
        for t0 in range(r0, r1, step):
            t1 = min(t0 + step, r1)
            a, b = covering(t0, t1)
            window = log_y[:, patch_rows(a - lo, b - lo, patch, overlap=True)]    # texture rows a:b-1+patch
            coefficients = U.T @ patch_matrix(window, patch, overlap=True)
            truth = window[:, t0 - a:t1 - a]      # every patch covering these rows is in the window
            sq_norm += float(np.sum(truth * truth))
            for i, k in enumerate(ks):
                blended = blend_patches(U[:, :k] @ coefficients[:k], window.shape, patch)
                sq_err[i] += float(np.sum((blended[:, t0 - a:t1 - a] - truth) ** 2))
    errors: list[float | None] = [None] * U.shape[1]
    for i, k in enumerate(ks):
        errors[k - 1] = float(np.sqrt(sq_err[i] / sq_norm))
    return errors


def leave_one_out(model_path: str, materials: Sequence[Material], material_id: str,
                  settings: ModelSettings) -> dict[str, Any]:
    """Projection errors of one material onto bases merged without it (thesis Table 1).

    ``class`` and ``global``: the ``log_y`` bases; ``abtf``: the class'
    ``abtf_log_y`` basis on all of the material's patches, blended back to
    texels (:func:`abtf_projection_errors`);
    ``fmf``: the material's own ``log_y`` basis (the thesis' FMF column).
    """
    group = zarr.open_group(model_path, mode="r", zarr_format=3)
    material = next(m for m in materials if m.material_id == material_id)
    merged = merge_bases(group, materials, settings, exclude=material_id, store=False,
                         bases=("log_y", "abtf_log_y"))
    own = read_basis(group, f"materials/{material_id}/log_y")
    band = band_budget(settings)
    return {
        "material": material_id, "class": material.cls,
        "class_basis": projection_errors(material.path, merged["log_y"][material.cls].U, max_bytes=band).tolist(),
        "global_basis": projection_errors(material.path, merged["log_y"]["__global__"].U, max_bytes=band).tolist(),
        "abtf_class_basis": abtf_projection_errors(material.path, merged["abtf_log_y"][material.cls].U,
                                                   settings.patch, work_budget(settings.memory_bytes)),
        "fmf": float(projection_errors(material.path, own.U, max_bytes=band)[-1]), "fmf_k": own.k,
    }


def table_1(results: Sequence[dict[str, Any]], ks: Sequence[int]) -> dict[str, dict[str, Any]]:
    """Mean leave-one-out errors per class at the given numbers of basis vectors (percent)."""
    table: dict[str, dict[str, Any]] = {}
    for cls in sorted({r["class"] for r in results}):
        rows = [r for r in results if r["class"] == cls]

        def at(key: str, k: int) -> float | None:
            values = [r[key][k - 1] for r in rows if len(r[key]) >= k and r[key][k - 1] is not None]
            return round(100 * float(np.mean(values)), 3) if len(values) == len(rows) else None

        table[cls] = {"fmf": round(100 * float(np.mean([r["fmf"] for r in rows])), 3),
                      **{f"class_{k}": at("class_basis", k) for k in ks},
                      **{f"global_{k}": at("global_basis", k) for k in ks},
                      **{f"abtf_{k}": at("abtf_class_basis", k) for k in ks}}
    return table


def with_k(settings: ModelSettings, **k: int | None) -> ModelSettings:
    """``settings`` with some per-material ``k`` replaced."""
    return replace(settings, k_material={**settings.k_material, **k})


# --------------------------------------------------------------------------- the whole build


def build_database(db: str | os.PathLike, out_dir: str | os.PathLike, client: Any, *,
                   settings: ModelSettings = ModelSettings(), class_map: dict[str, str] | None = None,
                   ks: Sequence[int] | None = None, overwrite: bool = False,
                   progress: Callable[[str], Callable[[int, int], None] | None] | None = None) -> dict[str, Any]:
    """Fit, merge and evaluate the model database of ``db`` into ``out_dir/model.zarr``.

    Per-material bases run as one Dask task per material; the merges are
    small SVDs in this process; the leave-one-out evaluation is again one
    task per material. Returns the summary the report is made from.

    An existing complete ``model.zarr`` is updated on a staging copy that replaces it once complete;
    ``overwrite`` replaces one of another sampling (:func:`model_target`).
    """
    materials = discover(db, class_map)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    target, staged = model_target(out / "model.zarr", materials, overwrite)
    model_path = str(target)
    group = open_model_store(model_path, materials)
    fits = run_all(client, fit_material, [(model_path, m, settings) for m in materials],
                   progress and progress("material bases"))
    merged = merge_bases(group, materials, settings)
    loo = run_all(client, leave_one_out, [(model_path, materials, m.material_id, settings) for m in materials],
                  progress and progress("leave-one-out"))
    k_max = min(len(r["class_basis"]) for r in loo)
    ks = [k for k in (ks or (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048)) if k <= k_max]
    group.attrs.update(to_json_attr({"materials": {m.material_id: {"class": m.cls, "btf": m.path,
                                                                   "ingest_hash": m.ingest_hash} for m in materials},
                                     "settings": asdict(settings), "complete": True}))
    if staged:
        commit_staged(out / "model.zarr", "build-db")
    model_path = str(out / "model.zarr")
    return {
        "model": model_path, "materials": [asdict(m) for m in materials],
        "fits": fits, "k": {basis: {name: model.k for name, model in d.items()} for basis, d in merged.items()},
        "spectra": {name: model.sigma.tolist() for name, model in merged["log_y"].items()},
        "leave_one_out": loo, "table_1": table_1(loo, ks), "ks": ks,
    }
