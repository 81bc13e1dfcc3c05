"""``btf reconstruct``: a measurement and a class basis of the model database -> a full BTF store.

The input is a measurement store (``btf-measurement``, :mod:`tasks.measurement`,
``measured = G B``) or a demultiplexed BTF store (``btf-texture``, ``G = I``: the
denoising methods). The solve operator is built once from the basis of the model
store (``btf build-db``) and ``G`` -- :func:`btfcore.acquisition.measurement_operator.measurement_solve_operator`
for the linear ALS basis, :func:`btfcore.acquisition.reconstruct.solve_operator` /
:func:`btfcore.acquisition.reconstruct.abtf_operator` on the measured rows for the log bases
-- and applied band of texture rows by band in one Dask graph. The output is a
``btf-texture`` store, built beside its destination (``X.partial.zarr``) and
renamed into place only once complete (:mod:`tasks.staging`): a failed or killed
run leaves no half-written output, and a rerun resumes the bands not written.

Which basis for which measurement (paper 1 §3.1; paper 4 §4, "we cannot infer
M log(B) from MB"):

* ``als`` (linear RGB, relative-error ALS): any measurement -- sparse
  single-light (``pinv``, ``tikhonov``), multiplexed or mixed (``direct``),
  full demultiplexable ones also ``projection`` / ``thresholded``;
* ``log_y`` (log Y with ``u_y``/``v_y`` for the chromaticities) and
  ``abtf_log_y`` (3x3 patches of log Y, chromaticities per texel): single-light
  measurements only (each row one light/view pair), mapped to log space first;
  ``pinv`` or ``tikhonov`` (``projection`` too for a full BTF).

Radiometric correction (``--white``, ``--colour-matrix``; a measurement store
itself is never corrected): the basis is then one of corrected BTFs, and with
per-LED RGB gains ``D_c`` the uncorrected measurement is ``G D_c B_c`` per
channel. Single-light rows (and BTF stores) are corrected before the solve,
each row by its LED's gain; multiplexed rows get one operator per channel on
``G D_c`` and the colour matrix after the solve (:class:`RowCorrection`).

See docs/measurement-store.md.
"""

from __future__ import annotations

import os
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import zarr
from scipy import sparse

from btfcore.model.colour import from_log_yuv, to_log_yuv
from btfcore.capture.radiometric import apply_colour_matrix, apply_led_calibration
from btfcore.acquisition.measurement_operator import (
    as_sparse_G,
    demultiplexing_matrix,
    is_single_light,
    measurement_solve_operator,
    single_light_rows,
)
from btfcore.acquisition.reconstruct import (
    LAMBDA_ALS,
    LAMBDA_NIELSEN,
    RECONSTRUCTION_METHODS,
    SolveOperator,
    abtf_halo,
    abtf_operator,
    apply,
    reconstruct_abtf,
    solve_operator,
    texture_variance,
)
from tasks.compute import run_all
from tasks.faults import kill_point
from tasks.buffers import reused_buffer
from tasks.integrity import read_chunk_rows
from tasks.staging import commit_staged, finish_interrupted_commit, staging_path, store_attrs
from tasks.stores.btf import LV_ORDER, SCHEMA_NAME, SCHEMA_VERSION, BtfStore, create_btf_store, open_btf_store
from tasks.stores.btf import band_rows as btf_band_rows
from tasks.stores.common import json_key, write_chunk_aligned
from tasks.stores.measurement import SCHEMA_NAME as MEASUREMENT_SCHEMA
from tasks.stores.measurement import open_measurement_store, read_G

__all__ = ["RECONSTRUCT_BASES", "ReconstructSettings", "build_operators", "check_inputs", "open_model",
           "reconstruct_band", "reconstruct_chunk", "reconstruct_store", "read_input"]

#: Bases ``btf reconstruct`` takes from a model store's class.
RECONSTRUCT_BASES: tuple[str, ...] = ("als", "log_y", "abtf_log_y")
_LOG_METHODS = ("pinv", "tikhonov", "projection")


@dataclass(frozen=True)
class ReconstructSettings:
    """What a reconstruction depends on besides its inputs (hashable: it keys resumption).

    Parameters
    ----------
    cls : str
        Material class whose merged basis is used (``classes/<cls>/<basis>``).
    basis : {'als', 'log_y', 'abtf_log_y'}
    method : {'pinv', 'tikhonov', 'direct', 'projection', 'thresholded'}
    lam : float, optional
        λ of :math:`\\lambda \\Sigma^{-1}`. ``tikhonov`` defaults to the thesis' value for the
        basis (paper 4: :data:`~btfcore.acquisition.reconstruct.LAMBDA_ALS` = 0.01 for ``als``,
        :data:`~btfcore.acquisition.reconstruct.LAMBDA_NIELSEN` = 40 for the log-space bases); ``direct``
        defaults to 0.
    k : int, optional
        Use only the first ``k`` basis vectors (default all).
    decile : float
        ``thresholded``: textures above this decile of variance are left out.
    """

    cls: str
    basis: str = "als"
    method: str = "pinv"
    lam: float | None = None
    k: int | None = None
    decile: float = 9.0

    def __post_init__(self) -> None:
        if self.basis not in RECONSTRUCT_BASES:
            raise ValueError(f"basis {self.basis!r} is unknown; choose one of {', '.join(RECONSTRUCT_BASES)}")
        if self.method not in RECONSTRUCTION_METHODS:
            raise ValueError(f"method {self.method!r} is unknown; choose one of {', '.join(RECONSTRUCTION_METHODS)}")
        if self.basis != "als" and self.method not in _LOG_METHODS:
            raise ValueError(f"--basis {self.basis} works in log space, where a multiplexed measurement cannot be "
                             f"fitted (paper 4, §4); method {self.method!r} needs --basis als "
                             f"(log bases take {', '.join(_LOG_METHODS)})")
        if self.k is not None and self.k < 1:
            raise ValueError(f"k must be >= 1, got {self.k}")
        if self.method == "tikhonov" and self.lam is None:      # the thesis' defaults (paper 4, §5)
            object.__setattr__(self, "lam", LAMBDA_ALS if self.basis == "als" else LAMBDA_NIELSEN)


# --------------------------------------------------------------------------- inputs


def open_model(model: str | os.PathLike) -> zarr.Group:
    """The model store of ``btf build-db``: ``MODEL_DIR/model.zarr`` or the store itself."""
    path = Path(model)
    if (path / "model.zarr").exists():
        path = path / "model.zarr"
    try:
        group = zarr.open_group(str(path), mode="r", zarr_format=3)
    except Exception:  # noqa: BLE001
        raise ValueError(f"{model}: no model store (MODEL_DIR/model.zarr from `btf build-db`)") from None
    if group.attrs.get("schema") != "btf-model":
        raise ValueError(f"{path}: schema {group.attrs.get('schema')!r}, not a model store; give the --out folder "
                         "of `btf build-db`")
    return group


def read_input(path: str | os.PathLike) -> tuple[zarr.Group, str]:
    """Open the input of a reconstruction: ``(group, kind)`` with kind ``"measurement"`` or ``"btf"``
    (:func:`tasks.stores.measurement.open_measurement_store`, :func:`tasks.stores.btf.open_btf_store`).

    Raises
    ------
    ValueError
        Not a finished measurement or BTF store.
    """
    attrs = store_attrs(path)
    if not attrs:
        raise ValueError(f"{path}: not a readable Zarr store; give the output of `btf ingest`")
    schema = attrs.get("schema")
    if schema == MEASUREMENT_SCHEMA:
        return open_measurement_store(path), "measurement"
    if schema == SCHEMA_NAME:
        return open_btf_store(path, produced_by="`btf ingest`, `btf resample` or `btf reconstruct`").group, "btf"
    raise ValueError(f"{path}: schema {schema!r}; give a measurement store (`btf ingest` of a plan capture) or "
                     f"a BTF store ({SCHEMA_NAME})")


def check_sampling(model: zarr.Group, data: zarr.Group, data_path: Any) -> None:
    """The basis' light/view rows must be the measurement's full rows (same order, same directions)."""
    ml, mv = model["light_dir"][...], model["view_dir"][...]
    dl, dv = data["light_dir"][...], data["view_dir"][...]
    if ml.shape != dl.shape:
        raise ValueError(f"{data_path}: its light/view sampling has {dl.shape[0]} pairs, the model's bases "
                         f"{ml.shape[0]}; reconstruct with a model built on this device's sampling, or resample "
                         "(btf resample) both to one sampling")
    bad = np.flatnonzero(~(np.isclose(ml, dl, atol=1e-9).all(1) & np.isclose(mv, dv, atol=1e-9).all(1)))
    if bad.size:
        r = int(bad[0])
        raise ValueError(f"{data_path}: light/view pair {r} differs from the model's (light {dl[r].round(6).tolist()} "
                         f"vs {ml[r].round(6).tolist()}, view {dv[r].round(6).tolist()} vs {mv[r].round(6).tolist()}"
                         f"; {bad.size} pairs differ): the basis was built on another sampling; use a model of "
                         "this device's sampling")


def _basis_names(basis: str) -> tuple[str, ...]:
    """The model groups (under ``classes/<cls>/``) a ``--basis`` reads."""
    return ("als",) if basis == "als" else (basis, "u_y", "v_y")


def _check_class(model: zarr.Group, cls: str, names: tuple[str, ...], model_path: Any) -> None:
    """``--class`` must name one of the model's classes, exactly (so never a path into the store, such as
    ``../../etc``), and that class must hold the bases ``names``.

    Raises
    ------
    ValueError
        One line naming the model, the class and the valid classes (or the
        class's bases).
    """
    classes = sorted(model["classes"].group_keys()) if "classes" in model else []
    if cls not in classes:
        kind = ("is a path, not a class name" if any(c in cls for c in "/\\") or cls in (".", "..")
                else "is not a class of this model")
        raise ValueError(f"{model_path}: --class {cls!r} {kind}; choose one of: "
                         f"{', '.join(classes) or 'none (the model has no class bases; rebuild it with btf build-db)'}")
    group = model[f"classes/{cls}"]
    missing = [n for n in names if n not in group]
    if missing:
        have = sorted(group.group_keys())
        raise ValueError(f"{model_path}: class {cls} has no basis {', '.join(missing)} (it has: "
                         f"{', '.join(have) or 'none'}); choose --basis from {', '.join(RECONSTRUCT_BASES)} by "
                         "what the class has, or build the model with that basis")


def class_basis(model: zarr.Group, cls: str, name: str, k: int | None,
                model_path: Any) -> tuple[np.ndarray, np.ndarray]:
    """The class ``cls``'s basis ``name`` of the opened model store: ``U (n_lv, k)`` and ``sigma (k,)``, its first
    ``k`` vectors (all for ``None``); a class or basis the store lacks, or ``k`` above its size, is refused
    naming ``model_path`` and what it holds."""
    from tasks.model import read_basis

    _check_class(model, cls, (name,), model_path)             # a class name never indexes the store as a path
    where = f"classes/{cls}/{name}"
    try:
        fit = read_basis(model, where)
    except KeyError:
        classes = sorted(model["classes"].group_keys()) if "classes" in model else []
        raise ValueError(f"{model_path}: no basis {where} in the model store (classes: {', '.join(classes) or 'none'}); "
                         "choose --class from them, or build the model with that class") from None
    U, sigma = np.asarray(fit.U, dtype=np.float64), np.asarray(fit.sigma, dtype=np.float64)
    for part, a in (("U", U), ("sigma", sigma)):
        bad = np.argwhere(~np.isfinite(a))
        if bad.size:
            raise ValueError(f"{model_path}: {where}/{part}{bad[0].tolist()} = {float(a[tuple(bad[0])])!r} is not "
                             "finite; rebuild the model with `btf build-db`")
    if k is not None:
        if k > U.shape[1]:
            raise ValueError(f"{model_path}: {where} has {U.shape[1]} basis vectors, k={k} asked; choose k <= "
                             f"{U.shape[1]}")
        U, sigma = U[:, :k], sigma[:k]
    return U, sigma


def _measurement_G(data: zarr.Group, kind: str) -> sparse.csr_matrix | None:
    """``G`` of a measurement store, read block of rows by block into a sparse matrix (dense, a full S-matrix
    capture at bonn-dome2's scale would take 5.5 GB); ``None`` for a BTF store (the identity)."""
    return None if kind == "btf" else read_G(data)


def _bands(h: int, n_rows: int, w: int) -> list[tuple[int, int]]:
    step = btf_band_rows(n_rows, h, w)
    return [(r, min(r + step, h)) for r in range(0, h, step)]


# --------------------------------------------------------------------------- operators


@dataclass(frozen=True)
class RowCorrection:
    """The radiometric correction of one reconstruction, prepared for its measurement.

    Attributes
    ----------
    gain : (n_lv, 3) ndarray
        RGB gain of the LED of every full light/view row (the white standard's
        per-LED gains repeated over the views).
    matrix : (3, 3) or (3, 4) ndarray or None
        Camera RGB -> target RGB, applied after the gains.
    measured_gain : (n_meas, 3) ndarray or None
        Gains of the measured rows when each measures one LED (single-light
        rows, a BTF store), or ones for a linear colour matrix without gains:
        the rows are then corrected before the solve. None for multiplexed
        rows with gains (or an affine matrix, whose offset does not commute
        with ``G``): the operators are then per channel on ``G D_c``.
    """

    gain: np.ndarray
    matrix: np.ndarray | None
    measured_gain: np.ndarray | None

    @classmethod
    def of(cls, led_gain: np.ndarray | None, matrix: np.ndarray | None,
           G: np.ndarray | sparse.csr_matrix | None, n_lv: int) -> "RowCorrection | None":
        if led_gain is None and matrix is None:
            return None
        matrix = None if matrix is None else np.asarray(matrix, dtype=np.float64)
        gain = np.ones((n_lv, 3)) if led_gain is None else \
            np.tile(np.asarray(led_gain, dtype=np.float64), (n_lv // len(led_gain), 1))
        if G is None or is_single_light(G):
            return cls(gain, matrix, gain if G is None else gain[single_light_rows(G)])
        if led_gain is None and matrix.shape[1] == 3:  # a linear matrix acts across channels, G across rows
            return cls(gain, matrix, np.ones((G.shape[0], 3)))
        return cls(gain, matrix, None)

    def rows(self, x: np.ndarray, gain: np.ndarray) -> np.ndarray:
        """Rows of ``x`` (rows, ..., 3) divided by their ``gain`` (rows, 3), then the colour matrix."""
        x = apply_led_calibration(np.asarray(x, dtype=np.float32), gain)             # eq. B = W / g_l
        return x if self.matrix is None else apply_colour_matrix(x, self.matrix).astype(np.float32, copy=False)


def _corrected_G(G: np.ndarray | sparse.csr_matrix | None, correction: RowCorrection | None) -> list[np.ndarray | sparse.csr_matrix | None]:
    """The measurement matrices the operators are built on: ``[G]``, or ``[G D_r, G D_g, G D_b]``
    for a multiplexed measurement of corrected radiance (its rows mix LEDs whose gains differ)."""
    if correction is None or correction.measured_gain is not None:
        return [G]
    return [as_sparse_G(as_sparse_G(G).multiply(correction.gain[None, :, c])) for c in range(3)]  # eq. G D_c




def build_operators(settings: ReconstructSettings, model: zarr.Group, G: np.ndarray | sparse.csr_matrix | None, n_lv: int,
                    variance: np.ndarray | None = None, model_path: Any = "model",
                    correction: RowCorrection | None = None) -> dict[str, SolveOperator]:
    """The solve operators of a reconstruction, by part: ``{"rgb"}`` (ALS), ``{"r", "g", "b"}`` (ALS on a
    multiplexed measurement with a radiometric correction) or ``{"y", "u", "v"}`` (log bases).

    Parameters
    ----------
    G : (n_meas, n_lv) ndarray, scipy.sparse matrix or None
        The measurement matrix; None for a full BTF (the identity).
    variance : (n_lv,) ndarray, optional
        ``thresholded``: per-texture variance of the demultiplexed BTF.
    correction : RowCorrection, optional
        The radiometric correction (per-channel operators on ``G D_c`` for multiplexed rows).

    Raises
    ------
    ValueError
        From the solve (too few rows for the basis without regularisation, rank),
        a multiplexed ``G`` with a log basis.
    """
    s = settings
    if s.basis == "als":
        U, sigma = class_basis(model, s.cls, "als", s.k, model_path)
        if G is None:
            return {"rgb": solve_operator(U, sigma, method=s.method, lam=s.lam, variance=variance, decile=s.decile)}
        Gs = _corrected_G(G, correction)
        return {part: measurement_solve_operator(U, Gc, sigma, method=s.method, lam=s.lam, variance=variance,
                                                 decile=s.decile)
                for part, Gc in zip(("rgb",) if len(Gs) == 1 else ("r", "g", "b"), Gs)}
    if G is not None and not is_single_light(G):
        raise ValueError(f"--basis {s.basis} reconstructs in log space, but the measurement has multiplexed rows "
                         "(log(M B) is not M log(B), paper 4 §4); use --basis als with --method direct")
    rows = None if G is None else single_light_rows(G)
    if s.method == "projection" and rows is not None and len(rows) != n_lv:
        raise ValueError("method 'projection' projects a full BTF; this measurement is sparse: use pinv or tikhonov")
    if s.method == "projection":
        rows = None
    ops: dict[str, SolveOperator] = {}
    for part, name in (("y", "log_y"), ("u", "u_y"), ("v", "v_y")):
        if part == "y" and s.basis == "abtf_log_y":
            U, sigma = class_basis(model, s.cls, "abtf_log_y", s.k, model_path)
            p = int(round(np.sqrt(U.shape[0] / n_lv)))
            if p * p * n_lv != U.shape[0]:
                raise ValueError(f"{model_path}: classes/{s.cls}/abtf_log_y has {U.shape[0]} rows, not p² x {n_lv}")
            if s.method == "projection":
                raise ValueError("--basis abtf_log_y reconstructs sparse measurements (pinv or tikhonov)")
            ops[part] = abtf_operator(U, np.arange(n_lv) if rows is None else rows, p=p, sigma=sigma,
                                      method=s.method, lam=s.lam)
            continue
        U, sigma = class_basis(model, s.cls, name, s.k if part == "y" else None, model_path)
        ops[part] = solve_operator(U, sigma, method=s.method, rows=rows, lam=s.lam)
    return ops


# --------------------------------------------------------------------------- applying


def reconstruct_chunk(ops: dict[str, SolveOperator], measured: np.ndarray, *, out_rows: tuple[int, int] | None = None,
                      height: int | None = None, correction: RowCorrection | None = None,
                      out: np.ndarray | None = None, part_rows: int | None = None,
                      on_rows: Callable[[slice], None] | None = None) -> np.ndarray:
    """Reconstruct a band of textures from measured ones (in memory).

    Parameters
    ----------
    ops : dict
        From :func:`build_operators`.
    measured : (n_meas, rows, w, 3) ndarray
        Measured textures of the band (for an ABTF basis: of its halo rows,
        :func:`btfcore.acquisition.reconstruct.abtf_halo`, or the whole texture).
    out_rows, height : optional
        ABTF basis: the output rows and the texture height.
    correction : RowCorrection, optional
        Radiometric correction: of the measured rows before the solve, or of
        the per-channel result after it.
    out : (n_lv, rows * w * 3) ndarray of float32, optional
        Buffer for the result of a float32 linear (``rgb``) operator; other operators ignore it.
    part_rows, on_rows : optional
        A linear (``rgb``) operator only: the light/view rows computed ``part_rows`` at a time, each
        finished slice handed to ``on_rows`` (:func:`btfcore.acquisition.reconstruct.apply`).

    Returns
    -------
    B : (n_lv, rows_out, w, 3) ndarray of float32
    """
    if correction is not None and correction.measured_gain is not None:
        measured = correction.rows(measured, correction.measured_gain)
    if "r" in ops:                                                   # per channel on G D_c, then the matrix
        out = np.stack([apply(ops[part], measured[..., i]) for i, part in enumerate("rgb")], axis=-1)
        out = out.astype(np.float32, copy=False)
        return out if correction.matrix is None else apply_colour_matrix(out, correction.matrix).astype(np.float32)
    if "rgb" in ops:
        buffer = out if ops["rgb"].dtype == np.float32 else None
        return apply(ops["rgb"], measured, out=buffer, part_rows=part_rows, on_rows=on_rows).astype(np.float32,
                                                                                                    copy=False)
    x = to_log_yuv(np.asarray(measured, dtype=np.float32))           # paper 1 §3.1: log Y, U/Y, V/Y
    if ops["y"].patch_size is not None:
        y = reconstruct_abtf(ops["y"], x[..., 0], out_rows=out_rows, height=height)
        lo = 0 if out_rows is None else out_rows[0] - abtf_halo(out_rows[0], out_rows[1], height,
                                                                  ops["y"].patch_size).start
        x = x[:, lo:lo + y.shape[1]]
    else:
        y = apply(ops["y"], x[..., 0])
    res = np.stack([y, apply(ops["u"], x[..., 1]), apply(ops["v"], x[..., 2])], axis=-1)
    return from_log_yuv(res.astype(np.float32, copy=False))


#: Parts of a band's light/view rows (whole chunks) that :func:`reconstruct_band` writes, each while the next is
#: solved (docs/benchmarks.md, 2026-12-05).
WRITE_PARTS = 8


def _check_output(out: np.ndarray, in_path: str, r0: int, r1: int) -> None:
    if not _all_finite(out):
        raise ValueError(f"{in_path}: the reconstruction of texture rows {r0}:{r1} is not finite (a log basis "
                         "extrapolated beyond the float range); use --method tikhonov or --basis als")


def _all_finite(a: np.ndarray) -> bool:
    """Whether ``a`` holds no NaN/Inf, without a boolean array of its size: a NaN or Inf makes the float sum
    non-finite; only then (or where finite values overflow it) are the elements tested. On this VM a
    fresh 130 MB mask of a 522 MB band costs its page faults on every band."""
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(a.sum()):
            return True
    return bool(np.isfinite(a).all())


def reconstruct_band(in_path: str, out_path: str, ops: dict[str, SolveOperator], band: int,
                     bands: list[tuple[int, int]], correction: RowCorrection | None = None) -> int:
    """Reconstruct texture rows ``bands[band]`` and write them (whole chunks of ``btf``), then its marker."""
    src = zarr.open_group(in_path, mode="r", zarr_format=3)
    arr = src["measured"] if "measured" in src else src["btf"]
    r0, r1 = bands[band]
    h = arr.shape[1]
    p = ops["y"].patch_size if "y" in ops else None
    rows = abtf_halo(r0, r1, h, p) if p is not None else slice(r0, r1)
    measured = reused_buffer("reconstruct-measured", (arr.shape[0], rows.stop - rows.start, *arr.shape[2:]), arr.dtype)
    read_chunk_rows(arr, rows.start, rows.stop, measured)
    if not _all_finite(measured):                       # named in the input's own indices, not the solve's
        finite = np.isfinite(measured)
        first = tuple(int(v) for v in np.argwhere(~finite)[0])
        idx = [first[0], first[1] + rows.start, *first[2:]]
        raise ValueError(f"{in_path}: {arr.basename}{idx} = {float(measured[first])!r} "
                         f"({int(measured.size - finite.sum())} NaN/Inf values in texture rows {rows.start}:"
                         f"{rows.stop}); write the input again with `btf ingest` (or the command that wrote it)")
    dst = BtfStore(out_path, "r+").group
    btf = dst["btf"]
    shape = (btf.shape[0], r1 - r0, *btf.shape[2:])
    if p is not None or "rgb" not in ops or ops["rgb"].dtype != np.float32:
        out = reconstruct_chunk(ops, measured, out_rows=(r0, r1) if p is not None else None, height=h,
                                correction=correction)
        _check_output(out, in_path, r0, r1)
        write_chunk_aligned(btf, (slice(None), slice(r0, r1)), out.reshape(shape))
    else:               # a worker thread's bands share one output buffer; one part is written while the next is solved
        buffer = reused_buffer("reconstruct-band", (ops["rgb"].n_out, measured[0].size), np.float32)
        part_rows = -(-btf.shape[0] // btf.chunks[0] // WRITE_PARTS) * btf.chunks[0]          # whole chunks
        with ThreadPoolExecutor(1) as writer:
            writes = []

            def write(rows: slice) -> None:
                _check_output(buffer[rows], in_path, r0, r1)
                part = buffer.reshape(shape)[rows]
                writes.append(writer.submit(write_chunk_aligned, btf, (rows, slice(r0, r1)), part))

            reconstruct_chunk(ops, measured, correction=correction, out=buffer, part_rows=part_rows, on_rows=write)
            for done in writes:
                done.result()
    kill_point("chunk-written")
    dst["written"][band] = 1
    return band


def _variance(in_path: str, G: np.ndarray | sparse.csr_matrix | None, bands: list[tuple[int, int]], client: Any,
              correction: RowCorrection | None = None) -> np.ndarray:
    """Per-texture variance of the demultiplexed (and corrected) BTF ``G^+ y``, streamed over bands on the cluster."""
    import dask

    P = None if G is None else demultiplexing_matrix(G)

    def band_block(r0: int, r1: int) -> np.ndarray:
        src = zarr.open_group(in_path, mode="r", zarr_format=3)
        arr = src["measured"] if "measured" in src else src["btf"]
        y = np.asarray(arr[:, r0:r1], dtype=np.float64)
        x = y if P is None else np.asarray(P @ y.reshape(y.shape[0], -1)).reshape((P.shape[0],) + y.shape[1:])
        if correction is not None:
            x = correction.rows(x, correction.gain)
        return x.reshape(x.shape[0], -1)

    blocks = client.compute([dask.delayed(band_block)(r0, r1) for r0, r1 in bands], sync=True)
    return texture_variance(iter(blocks))


def _correction(data: zarr.Group, kind: str, G: np.ndarray | sparse.csr_matrix | None, calibration: Any, in_path: Any
                ) -> RowCorrection | None:
    """The :class:`RowCorrection` of ``calibration`` (:class:`tasks.radiometric.Calibration`) for this input."""
    if calibration is None:
        return None
    if data.attrs.get("radiometric"):
        raise ValueError(f"{in_path}: the {kind} store is already radiometrically corrected "
                         f"({data.attrs.get('radiometric')}); reconstruct it without --white/--colour-matrix")
    n_turn, n_cam, n_leds = data.attrs["turntable_cameras_leds"]
    if calibration.led_gain is not None and len(calibration.led_gain) != n_leds:
        raise ValueError(f"{calibration.info.get('white_standard')}: the white standard has "
                         f"{len(calibration.led_gain)} LEDs, the measurement {in_path} {n_leds}; "
                         "calibrate with a white standard captured on the same dome")
    return RowCorrection.of(calibration.led_gain, calibration.colour_matrix, G, n_turn * n_cam * n_leds)


def check_inputs(in_path: str | os.PathLike, model_path: str | os.PathLike, settings: ReconstructSettings,
                 calibration: Any = None) -> None:
    """Every check of :func:`reconstruct_store` that needs no cluster (``btf reconstruct`` runs it before one
    starts): the input and model stores, the class (one of the model's, by name) and its bases, their
    light/view samplings, the basis and the solve itself.

    Raises
    ------
    ValueError
        As :func:`reconstruct_store`.
    """
    data, kind = read_input(in_path)
    model = open_model(model_path)
    _check_class(model, settings.cls, (), model_path)
    check_sampling(model, data, in_path)
    n_turn, n_cam, n_leds = data.attrs["turntable_cameras_leds"]
    G = _measurement_G(data, kind)
    correction = _correction(data, kind, G, calibration, in_path)
    if settings.method != "thresholded":                  # its operator needs a pass over the data
        build_operators(settings, model, G, n_turn * n_cam * n_leds, None, model_path, correction)
    else:                                                 # but its basis must be there
        _check_class(model, settings.cls, _basis_names(settings.basis), model_path)


def reconstruct_hash(data: zarr.Group, model: zarr.Group, settings: ReconstructSettings,
                     band: int | None = None, calibration: Any = None) -> str:
    """What the output depends on: the input's ingest hash, the basis keys, the settings."""
    names = ("als",) if settings.basis == "als" else (settings.basis, "u_y", "v_y")
    keys = {}
    for n in names:
        try:
            keys[n] = model[f"classes/{settings.cls}/{n}"].attrs.get("key")
        except KeyError:
            keys[n] = None
    payload = {"input": data.attrs.get("ingest_hash") or data.attrs.get("reconstruct_hash"), "bases": keys,
               "rows_id": model.attrs.get("rows_id"), "settings": asdict(settings), "schema": f"{SCHEMA_NAME}/{SCHEMA_VERSION}",
               "band": band, "calibration": None if calibration is None else calibration.key()}
    return json_key(payload)


def _create_output(path: Path, data: zarr.Group, key: str, attrs: dict[str, Any], n_bands: int, band: int
                   ) -> BtfStore:
    """The output BTF store: the input's rows and directions, one resume marker per band of texture rows."""
    h, w = data.attrs["texture_shape"]
    n_leds = data.attrs["turntable_cameras_leds"][2]
    return create_btf_store(path, {**attrs, "reconstruct_hash": key, "ingest_hash": key},
                            light_dir=data["light_dir"][...], view_dir=data["view_dir"][...],
                            lv_index=data["lv_index"][...], texture_shape=(h, w), rows_per_chunk=n_leds, band=band,
                            written_shape=(n_bands,))


def reconstruct_store(in_path: str | os.PathLike, model_path: str | os.PathLike, out_path: str | os.PathLike,
                      settings: ReconstructSettings, client: Any, *, overwrite: bool = False,
                      band_rows: int | None = None, calibration: Any = None,
                      progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Reconstruct a full BTF store from a measurement (or a BTF) and a class basis, on a Dask cluster.

    Parameters
    ----------
    in_path : str or path-like
        A finished measurement store or BTF store.
    model_path : str or path-like
        ``btf build-db`` output folder (or its ``model.zarr``).
    out_path : str or path-like
        The BTF store to write (.zarr). It is built at ``X.partial.zarr`` and
        renamed into place once every band is written; a rerun resumes the
        partial store of the same inputs and settings.
    settings : ReconstructSettings
    client : distributed.Client
    overwrite : bool
        Replace another store at ``out_path`` (only once the new one is complete).
    band_rows : int, optional
        Texture rows per band (a Dask task and a chunk of the output); default
        one BTF-store chunk, :func:`tasks.stores.btf.band_rows`.
    calibration : tasks.radiometric.Calibration, optional
        Radiometric correction of the (uncorrected) measurement, for a model
        of corrected BTFs (:class:`RowCorrection`).

    Returns
    -------
    summary : dict
        Bands processed/skipped, the operator's condition number, seconds.

    Raises
    ------
    ValueError
        Bad input, before anything is written: not a measurement/BTF store, no
        such class or basis, another light/view sampling than the model's,
        fewer measured rows than basis vectors with ``pinv`` (suggesting
        ``tikhonov``), a multiplexed measurement with a log basis.
    FileExistsError
        Another store at ``out_path`` without ``overwrite``.
    """
    start = time.perf_counter()
    data, kind = read_input(in_path)
    model = open_model(model_path)
    _check_class(model, settings.cls, (), model_path)   # before a store path uses the class name
    check_sampling(model, data, in_path)
    out = Path(out_path)
    key = reconstruct_hash(data, model, settings, band_rows, calibration)
    finish_interrupted_commit(out)
    existing = store_attrs(out)
    if existing is not None and not overwrite:
        if existing.get("reconstruct_hash") == key and existing.get("complete"):
            return {"bands_processed": 0, "bands_skipped": None, "out": str(out), "seconds": 0.0, "reused": True}
        raise FileExistsError(f"{out} holds {'another store' if existing else 'something that is not a Zarr store'} "
                              f"(reconstruct_hash {existing.get('reconstruct_hash') if existing else None!r}, this run "
                              f"{key!r}); choose another --out or pass --overwrite (the new store is built in "
                              f"{staging_path(out)} and replaces it only once complete)")
    G = _measurement_G(data, kind)
    h, w = data.attrs["texture_shape"]
    n_turn, n_cam, n_leds = data.attrs["turntable_cameras_leds"]
    n_lv = n_turn * n_cam * n_leds
    bands = _bands(h, n_leds, w) if band_rows is None else [(r, min(r + band_rows, h)) for r in range(0, h, band_rows)]
    band = bands[0][1]
    correction = _correction(data, kind, G, calibration, in_path)
    variance = _variance(str(in_path), G, bands, client, correction) if settings.method == "thresholded" else None
    ops = build_operators(settings, model, G, n_lv, variance, model_path, correction)   # bad input raises here
    condition = float(ops["y"].condition) if "y" in ops else max(float(op.condition) for op in ops.values())
    staging = staging_path(out)
    attrs_stage = store_attrs(staging)
    if attrs_stage is not None and attrs_stage.get("reconstruct_hash") == key:
        store = BtfStore(staging, "r+")                                  # a killed run: resume its bands
    else:
        if attrs_stage is not None:
            shutil.rmtree(staging)
        from tasks.radiometric import CALIBRATED_UNITS

        units = CALIBRATED_UNITS if calibration is not None and calibration.led_gain is not None else \
            data.attrs.get("units")
        attrs = {"units": units, "lv_order": LV_ORDER,
                 "turntable_cameras_leds": [n_turn, n_cam, n_leds], "material": data.attrs.get("material"),
                 "source": str(in_path), "settings": data.attrs.get("settings"),
                 "radiometric": None if calibration is None else calibration.info,
                 "reconstructed_from": {"input": str(in_path), "input_kind": kind, "model": str(model_path),
                                        "rows_id": model.attrs.get("rows_id"), **asdict(settings),
                                        "n_meas": int(G.shape[0]) if G is not None else n_lv,
                                        "condition": condition if np.isfinite(condition) else None,
                                        "plan": data.attrs.get("plan")}}
        store = _create_output(staging, data, key, attrs, len(bands), band)
    written = store.written
    pending = np.flatnonzero(written == 0).tolist()
    ops_f = client.scatter(ops, broadcast=True)                      # sent once to each worker, not per band
    run_all(client, reconstruct_band, [(str(in_path), str(staging), ops_f, b, bands, correction) for b in pending],
            progress)
    store.mark_complete("bands")
    commit_staged(out, "reconstruct")
    return {"out": str(out), "bands_processed": len(pending), "bands_skipped": int(written.size - len(pending)),
            "n_meas": int(G.shape[0]) if G is not None else n_lv, "n_lv": n_lv,
            "condition": condition if np.isfinite(condition) else None, "reused": False,
            "seconds": round(time.perf_counter() - start, 3)}
