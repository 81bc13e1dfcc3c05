"""Leave-one-out evaluation of sparse, multiplexed and combined acquisition (DESIGN stage 12, issue 5 item 6).

``btf evaluate acquisition --db DB --out OUT`` measures every acquisition
strategy of the thesis against the full ground truth of a simulated database:

1. **Truth database** (:func:`ensure_truth_database`): one ``btf-texture``
   store per material, rendered straight from the virtual dome's
   renderer (:func:`btfcore.simulate.render.render_view` at 2x, box
   down-sampled, as ``tasks.simulate`` makes its truth), one Dask task per
   view. :func:`tasks.model.discover` accepts them, so the model database
   fits its bases on them.
2. **Bases** (:func:`fit_bases`): per-material bases by
   :func:`tasks.model.fit_material` (one Dask task per material); per held-out
   material the class bases are merged *without* it
   (:func:`tasks.model.merge_bases` with ``exclude``), as the leave-one-out
   evaluation of ``btf build-db`` does.
3. **Measurements** simulated in BTF space from the truth with the sensor
   model of :mod:`btfcore.acquisition.noise`: single-light rows, and S-matrix patterns
   per view summed from the linear truth before the noise. Each image is
   exposed so that its brightest value sits at ``fill`` of the full well.
4. **Reconstruction** with :mod:`btfcore.acquisition.reconstruct`, chunked over bands of
   texture rows: every stage is one Dask graph over (material, band) tasks
   (maxima -> exposure; demultiplexed variances -> thresholded operator;
   reconstruction and error sums), the operators built once per held-out
   material.
5. **Scores** (:mod:`btfcore.metrics` reduced over bands): relative L2 on
   log Y, mRMSE, mPSNR, mRE; renderings (:mod:`tasks.render`) of
   reconstruction and truth and their PSNR.

See ``docs/evaluation.md`` for the scale, the noise model, the strategies
and the claims.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from btfcore.model.colour import from_log_yuv, log_luminance, to_log_yuv
from btfcore.capture.demultiplex import demultiplex_operator
from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.noise import SensorNoise, expose, exposure_gain
from btfcore.acquisition.reconstruct import (
    LAMBDA_ALS,
    SolveOperator,
    abtf_halo,
    abtf_operator,
    apply,
    reconstruct_abtf,
    solve_operator,
)
from btfcore.acquisition.sampling import multiplexed_basis, parabolic_map_sampling, random_swap
from btfcore.dome import DEVICE_NAMES, Device, get_device
from btfcore.simulate.materials import MATERIAL_CLASSES
from tasks.integrity import create_array
from tasks.model import (
    CHANNELS,
    LINEAR_SVD,
    Material,
    ModelSettings,
    discover,
    fit_material,
    merge_bases,
    open_model_store,
)
from tasks.staging import begin_store, finish_store, store_attrs
from tasks.stores import to_json_attr

#: The thesis' sparse pair counts (paper 4 §5.2: n_s of 2,376 (light, turntable) pairs, all 11 cameras).
THESIS_N_S = (100, 200, 400)
#: (light, turntable) pairs of the thesis' dome (198 LEDs x 12 positions).
THESIS_PAIRS = 198 * 12
#: Classes of claim (a) (paper 1 Table 2: the structured classes).
STRUCTURED_CLASSES = ("carpet", "stone", "leather")
#: Marks a truth store written by this module.
TRUTH_KIND = "evaluation-truth"


# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class EvaluationConfig:
    """Everything the acquisition evaluation depends on; its hash keys the truth stores.

    Parameters
    ----------
    device : str
        Dome preset (:data:`btfcore.dome.DEVICE_NAMES`).
    n_turntable : int or None
        Keep the first turntable positions (None: all).
    texture_size : int or None
        Texture side (the truth is rendered at twice this and box-filtered).
    materials_per_class : int
        Materials per class; leave-one-out needs at least 2.
    classes : tuple of str
        Material classes.
    seed : int
        Root seed of materials, samplings and noise.
    band_rows : int
        Texture rows per Dask task (the unit of the chunked reconstruction).
    fill : float
        Brightest value of each image at this fraction of the full well.
    sampling_steps : int
        Steps of the random-swap sampler (paper 1 Alg. 1).
    abrdf_k_fraction : float
        ABRDF bases use at most this fraction of the parabolic-map sample count
        as basis vectors (paper 1: 1024 vectors from 1,369 samples).
    als_iterations : int
        Iterations of the relative-error ALS bases (paper 4).
    als_components : int or None
        Vectors of the per-material ALS bases (None: the thesis' 64).
    render_materials : int
        Materials (the first of each class, in class order) whose
        reconstructions are written and rendered.
    render_size : int
        Side of the renderings, pixels.
    keep_reconstructions : bool
        Keep the rendered materials' reconstruction stores (about 50 MB per
        strategy at the default scale); by default they are removed once
        rendered.
    """

    device: str = "bonn-dome2"
    n_turntable: int | None = 2
    texture_size: int | None = 32
    materials_per_class: int = 2
    classes: tuple[str, ...] = MATERIAL_CLASSES
    seed: int = 0
    band_rows: int = 8
    fill: float = 0.8
    sampling_steps: int = 1500
    abrdf_k_fraction: float = 0.75
    als_iterations: int = 6
    als_components: int | None = 32
    render_materials: int = 1
    render_size: int = 64
    keep_reconstructions: bool = False

    def __post_init__(self) -> None:
        problems = []
        if self.device not in DEVICE_NAMES:
            problems.append(f"device {self.device!r} is unknown; choose one of {', '.join(DEVICE_NAMES)}")
        bad = [c for c in self.classes if c not in MATERIAL_CLASSES]
        if bad or not self.classes:
            problems.append(f"classes {bad or '[]'} are unknown; choose from {', '.join(MATERIAL_CLASSES)}")
        if self.materials_per_class < 1:
            problems.append(f"materials_per_class must be >= 1, got {self.materials_per_class}")
        if self.texture_size is not None and self.texture_size < 6:
            problems.append(f"texture_size must be >= 6 (3x3 ABTF patches), got {self.texture_size}")
        if self.n_turntable is not None and self.n_turntable < 1:
            problems.append(f"n_turntable must be >= 1, got {self.n_turntable}")
        if self.band_rows < 1:
            problems.append(f"band_rows must be >= 1, got {self.band_rows}")
        if not 0 <= self.render_materials <= len(self.classes):
            problems.append(f"render_materials must lie in [0, {len(self.classes)}] (one per class), "
                            f"got {self.render_materials}")
        if not 0 < self.abrdf_k_fraction <= 1:
            problems.append(f"abrdf_k_fraction must lie in (0, 1], got {self.abrdf_k_fraction}")
        if problems:
            raise ValueError("invalid evaluation config: " + "; ".join(problems))

    def build_device(self) -> Device:
        """The dome with the config's texture size and turntable positions."""
        overrides: dict[str, Any] = {}
        if self.texture_size is not None:
            overrides["texture_shape"] = (self.texture_size, self.texture_size)
        device = get_device(self.device, **overrides)
        if self.n_turntable is not None:
            device = device.with_overrides(turntable_angle_deg=device.turntable_angle_deg[: self.n_turntable])
        return device

    def truth_key(self) -> str:
        """Hash of what determines the truth stores (device, texture, materials, seed)."""
        payload = {"device": self.device, "n_turntable": self.n_turntable, "texture_size": self.texture_size,
                   "classes": list(self.classes), "materials_per_class": self.materials_per_class,
                   "seed": self.seed, "schema": "btf-texture/1.0"}
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["classes"] = list(self.classes)
        return d

    def model_settings(self) -> ModelSettings:
        """Model settings of the leave-one-out bases (the thesis' k capped by the data)."""
        # randomized subspace iteration: with n_lv > texels the Gram route's eigh of an n_lv x n_lv matrix
        # dominates (about 30 s per channel at 4,356 rows on one core)
        # ALS with als_components vectors: its cost grows with their square and dominated the fit
        # the VMV de-noising basis (a plain truncated SVD of linear RGB): paper 4's 64 linear vectors, or the
        # rank of the noise-free truth where that is lower (the wood BTFs have rank ~23 in linear RGB)
        return ModelSettings(k_material={"log_y": None, "u_y": None, "v_y": None, "abtf_log_y": None,
                                         "als": self.als_components, LINEAR_SVD: None},
                             als_iterations=self.als_iterations, seed=self.seed, method="randomized")


@dataclass(frozen=True)
class TruthSpec:
    """One material of the truth database."""

    index: int
    material_id: str
    class_name: str
    seed: int


def truth_specs(config: EvaluationConfig) -> list[TruthSpec]:
    """Materials of the truth database: ``materials_per_class`` of every class, classes round-robin."""
    specs = []
    for index in range(config.materials_per_class * len(config.classes)):
        cls = config.classes[index % len(config.classes)]
        seed = int(np.random.SeedSequence([config.seed, 7331, index]).generate_state(1)[0])
        specs.append(TruthSpec(index, f"{index:03d}-{cls}", cls, seed))
    return specs


def scaled_pairs(n_s: int, n_pairs: int) -> int:
    """The thesis' ``n_s`` of 2,376 (light, turntable) pairs scaled to a device with ``n_pairs`` pairs."""
    return max(1, int(round(n_s * n_pairs / THESIS_PAIRS)))


# --------------------------------------------------------------------------- 1. the truth database


def _truth_hash(config: EvaluationConfig, spec: TruthSpec) -> str:
    return hashlib.sha256(f"{config.truth_key()}/{spec.material_id}/{spec.seed}".encode()).hexdigest()[:16]


def create_truth_store(path: Path, config: EvaluationConfig, spec: TruthSpec, device: Device) -> zarr.Group:
    """An empty truth store (``btf-texture`` 1.0, rows ``(turntable, camera, light)``), one chunk per view."""
    h, w = device.texture_shape
    group = begin_store(path)
    create_array(group, "btf", shape=(device.n_lv, h, w, 3), chunks=(device.n_leds, h, w, 3), dtype="float32",
                       fill_value=0.0, compressors=None, dimension_names=["lv", "tex_row", "tex_col", "channel"])
    light, view, lv_index = device.lv_directions()
    for name, data in (("light_dir", light), ("view_dir", view), ("lv_index", lv_index)):
        create_array(group, name, shape=data.shape, dtype=data.dtype, chunks=data.shape, compressors=None)[...] = data
    group.attrs.put(to_json_attr({
        "schema": "btf-texture", "schema_version": "1.0", "complete": False, "kind": TRUTH_KIND,
        "units": "radiance per unit irradiance (BTF value incl. cos theta_i), noise-free ground truth",
        "lv_order": ["turntable", "camera", "light"], "texture_shape": [h, w],
        "turntable_cameras_leds": [device.n_turn, device.n_cam, device.n_leds],
        "ingest_hash": _truth_hash(config, spec), "evaluation": config.to_json(),
        "material": {"material_id": spec.material_id, "class": spec.class_name, "seed": spec.seed},
    }))
    return finish_store(path, group)


def prepare_truth_material(spec: TruthSpec, config: EvaluationConfig) -> tuple[Any, np.ndarray]:
    """The material's maps at twice the texture resolution and its horizon map."""
    from btfcore.simulate.materials import make_material
    from btfcore.simulate.render import horizon_map
    from tasks.textures import load_texture_sources

    h, w = config.build_device().texture_shape
    maps = make_material(spec.class_name, spec.seed, (2 * h, 2 * w), load_texture_sources())
    return maps, horizon_map(maps.height)


def render_truth_view(path: str, config: EvaluationConfig, prepared: tuple[Any, np.ndarray], t: int, c: int) -> int:
    """Render the truth of one view (all lights) at 2x, box-filter it and write its chunk."""
    from btfcore.simulate.render import downsample2, render_view

    device = config.build_device()
    maps, horizon = prepared
    truth = downsample2(render_view(maps, device.view_dir(t, c), device.light_dirs(t), horizon))
    v = t * device.n_cam + c
    btf = zarr.open_group(path, mode="r+", zarr_format=3)["btf"]
    btf[v * device.n_leds:(v + 1) * device.n_leds] = truth.astype(np.float32)
    return v


def ensure_truth_database(config: EvaluationConfig, db: str | os.PathLike, client: Any, *,
                          progress: Callable[[int, int], None] | None = None) -> list[str]:
    """Write the truth stores of ``config`` into ``db`` (reusing finished ones), one Dask task per view.

    Raises
    ------
    ValueError
        When a store at one of the paths holds something else (another
        configuration's truth, or not a truth store): nothing is overwritten.
    """
    from distributed import as_completed

    db = Path(db)
    db.mkdir(parents=True, exist_ok=True)
    device = config.build_device()
    futures, paths = [], []
    for spec in truth_specs(config):
        path = db / f"{spec.material_id}.zarr"
        paths.append(str(path))
        attrs = store_attrs(path)
        if attrs is not None:
            if attrs.get("kind") != TRUTH_KIND or attrs.get("ingest_hash") != _truth_hash(config, spec):
                if attrs.get("kind") == TRUTH_KIND and not attrs.get("complete"):
                    pass                                        # our own unfinished store: rewrite it
                else:
                    raise ValueError(f"{path}: holds {'another configuration of the' if attrs.get('kind') == TRUTH_KIND else 'something other than a'} "
                                     "truth store of this evaluation; choose another --db or remove the store")
            elif attrs.get("complete"):
                continue
        create_truth_store(path, config, spec, device)
        prepared = client.submit(prepare_truth_material, spec, config, pure=False)
        futures += [client.submit(render_truth_view, str(path), config, prepared, t, c, pure=False)
                    for t in range(device.n_turn) for c in range(device.n_cam)]
    for done, future in enumerate(as_completed(futures), 1):
        future.result()
        if progress is not None:
            progress(done, len(futures))
    for path in paths:
        group = zarr.open_group(path, mode="r+", zarr_format=3)
        if not group.attrs.get("complete"):
            group.attrs.update({"complete": True})
    return paths


# --------------------------------------------------------------------------- 2. bases


def fit_bases(model_path: str, materials: Sequence[Material], settings: ModelSettings, client: Any, *,
              progress: Callable[[int, int], None] | None = None) -> list[dict[str, Any]]:
    """Per-material bases of every material (:func:`tasks.model.fit_material`), one Dask task each;
    a rerun reuses every stored basis whose key is unchanged."""
    from distributed import as_completed

    open_model_store(model_path, materials)
    futures = [client.submit(fit_material, model_path, m, settings, EVAL_BASES, pure=False) for m in materials]
    for done, future in enumerate(as_completed(futures), 1):
        future.result()
        if progress is not None:
            progress(done, len(futures))
    return [f.result() for f in futures]


#: Bases the evaluation reconstructs with.
EVAL_BASES = ("log_y", "u_y", "v_y", "abtf_log_y", "als", LINEAR_SVD)


def leave_one_out_bases(model_path: str, materials: Sequence[Material], material_id: str,
                        settings: ModelSettings) -> dict[str, Any]:
    """The class bases of ``material_id``'s class merged without it, ``{basis: TruncatedSVD}``.

    Raises
    ------
    ValueError
        When the model store lacks a per-material basis a merge needs (names
        the group; run the fit again) or the class has no other material.
    """
    group = zarr.open_group(model_path, mode="r", zarr_format=3)
    material = next((m for m in materials if m.material_id == material_id), None)
    if material is None:
        raise ValueError(f"{model_path}: material {material_id!r} is not in the database")
    others = [m for m in materials if m.cls == material.cls and m.material_id != material_id]
    if not others:
        raise ValueError(f"class {material.cls!r} has no material besides {material_id}: the leave-one-out "
                         "bases need another; add materials of that class")
    for m in materials:
        for basis in EVAL_BASES:
            where = f"materials/{m.material_id}/{basis}"
            if where not in group or "U" not in group[where] or not group[where].attrs.get("key"):
                raise ValueError(f"{model_path}: basis {where} is missing (an unfinished or other model store); "
                                 "run the fit again (delete the model store to start over)")
    merged = merge_bases(group, materials, settings, exclude=material_id, store=False, bases=EVAL_BASES,
                         classes=[material.cls])
    return {basis: merged[basis][material.cls] for basis in EVAL_BASES}


# --------------------------------------------------------------------------- 3.-4. strategies and operators


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

    ``space`` is ``'log'`` (log Y, U/Y, V/Y bases, one operator per channel;
    ``log_y`` may be an ABTF operator) or ``'linear'`` (the ALS basis on RGB).
    ``source`` is the measurement it reads: ``'single'`` (single-light rows),
    ``'demux'`` (the demultiplexed multiplexed measurement) or ``'mux'`` (the
    multiplexed rows themselves). ``rows`` index that source (None: all).
    ``operators`` is ``{channel: SolveOperator}`` (log) or ``{'rgb': ...}``
    (linear); an empty dict means "no reconstruction" (the plain
    demultiplexed BTF). ``info`` is reported.
    """

    name: str
    space: str
    source: str
    rows: np.ndarray | None
    operators: dict[str, SolveOperator]
    info: dict[str, Any] = field(default_factory=dict)


def _groups(geometry: Geometry, per_view: int) -> np.ndarray:
    """Group id ``turntable * per_view + j`` of every row ``(turntable, camera, j)`` (all cameras together)."""
    t = np.repeat(np.arange(geometry.n_turn), geometry.n_cam * per_view)
    j = np.tile(np.arange(per_view), geometry.n_views)
    return t * per_view + j


def _rows_of_groups(units: np.ndarray, geometry: Geometry, per_view: int) -> np.ndarray:
    """Rows (view-major, ``j`` fastest) of the chosen groups ``turntable * per_view + j``, sorted."""
    t, j = np.divmod(np.asarray(units, dtype=np.int64), per_view)
    rows = ((t[:, None] * geometry.n_cam + np.arange(geometry.n_cam)[None]) * per_view + j[:, None]).ravel()
    return np.sort(rows)


def build_strategies(bases: dict[str, Any], geometry: Geometry, light_dir: np.ndarray, view_dir: np.ndarray,
                     config: EvaluationConfig, variance: np.ndarray, patterns: np.ndarray,
                     seed: int) -> tuple[list[Strategy], dict[str, Any]]:
    """Samplings and solve operators of every strategy for one held-out material.

    Parameters
    ----------
    bases : dict
        :func:`leave_one_out_bases`.
    variance : (n_lv,) ndarray
        Per-texture variance of the linear demultiplexed RGB, over texels and channels (the
        thresholded de-noising, VMV §4.1: "unnormalised" data).
    patterns : (n_p, n_leds) ndarray
        S-matrix patterns of every view.

    Returns
    -------
    strategies, sampling : list of Strategy, dict
        ``sampling`` reports the sample counts, condition numbers and the
        selected (turntable, LED / pattern) pairs of the sparse strategies.
    """
    n_lv = geometry.n_lv
    strategies: list[Strategy] = []
    sampling: dict[str, Any] = {}

    # ---- paper 1: ABRDF vs ABTF, parabolic map vs optimised (log space, pinv)
    pmap = np.asarray(parabolic_map_sampling(light_dir, view_dir, 7), dtype=np.int64)
    n_pm = len(pmap)
    U = {c: bases[c].U for c in CHANNELS}
    k_a = int(min(U["log_y"].shape[1], max(1, int(config.abrdf_k_fraction * n_pm))))
    opt = random_swap(U["log_y"][:, :k_a], n_pm, max_steps=config.sampling_steps, seed=seed)
    U_t = bases["abtf_log_y"].U
    k_t = int(U_t.shape[1])
    sampling["paper1"] = {"n_samples": n_pm, "fraction": n_pm / n_lv, "k_abrdf": k_a, "k_abtf": k_t,
                          "kappa_optimized": opt.kappa}
    for label, rows in (("pmap7", pmap), ("optimized", np.asarray(opt.rows, dtype=np.int64))):
        ops = {c: solve_operator(U[c][:, :min(k_a, U[c].shape[1], len(rows))], method="pinv", rows=rows,
                                 fused=False) for c in CHANNELS}
        strategies.append(Strategy(f"abrdf-{label}", "log", "single", rows, ops,
                                   {"paper": "1", "basis": "ABRDF (log Y, U/Y, V/Y)", "k": k_a,
                                    "n_meas": int(len(rows)), "kappa_log_y": ops["log_y"].condition}))
        abtf = abtf_operator(U_t, rows, p=3, method="pinv")
        strategies.append(Strategy(f"abtf-{label}", "log", "single", rows, {**ops, "log_y": abtf},
                                   {"paper": "1", "basis": "3x3 ABTF for log Y, ABRDF for U/Y and V/Y", "k": k_t,
                                    "n_meas": int(len(rows)), "kappa_log_y": abtf.condition}))
    all_rows = np.arange(n_lv)
    strategies.append(Strategy("abrdf-projection", "log", "truth", None,
                               {c: solve_operator(U[c][:, :k_a], method="projection", fused=False) for c in CHANNELS},
                               {"paper": "1", "basis": "ABRDF", "k": k_a, "note": "truth projected (lower bound)"}))
    strategies.append(Strategy("abtf-projection", "log", "truth", all_rows,
                               {**{c: solve_operator(U[c][:, :k_a], method="projection", fused=False)
                                   for c in CHANNELS}, "log_y": abtf_operator(U_t, all_rows, p=3, method="pinv")},
                               {"paper": "1", "basis": "3x3 ABTF", "k": k_t, "note": "truth projected (lower bound)"}))

    # ---- VMV §4.1: plain demultiplexing, projection and thresholded de-noising, in linear RGB on the
    # class's truncated SVD of linear RGB BTFs ("D ~ U Sigma V^T"), the variance of the linear
    # (unnormalised) demultiplexed textures; scored in log Y like every strategy
    svd = bases[LINEAR_SVD]
    k_dn = int(svd.U.shape[1])
    strategies.append(Strategy("demultiplexed", "log", "demux", None, {}, {"paper": "VMV", "note": "no model"}))
    strategies.append(Strategy("projection", "linear", "demux", None,
                               {"rgb": solve_operator(svd.U, method="projection", fused=False)},
                               {"paper": "VMV eq. den Brok", "basis": "class truncated SVD (linear RGB)", "k": k_dn}))
    thr = solve_operator(svd.U, method="thresholded", variance=variance, fused=False)
    strategies.append(Strategy("thresholded", "linear", "demux", None, {"rgb": thr},
                               {"paper": "VMV §4.1", "basis": "class truncated SVD (linear RGB)", "decile": 9, "k": k_dn,
                                "variance": "linear demultiplexed RGB per texture",
                                "condition": thr.condition}))

    # ---- paper 4: ALS basis, sparse (pinv / Tikhonov), multiplexed (eq. 10), sparse + multiplexed
    als = bases["als"]
    Ua, sa = als.U, als.sigma
    k_als = int(Ua.shape[1])
    n_pairs = geometry.n_turn * geometry.n_leds
    groups_l = _groups(geometry, geometry.n_leds)
    US = Ua * sa[None, :]
    sampling["paper4"] = {"k_als": k_als, "n_pairs": n_pairs, "counts": {}}
    for n_thesis in THESIS_N_S:
        n_s = scaled_pairs(n_thesis, n_pairs)
        # with fewer measured rows than vectors, kappa is taken on the leading vectors the rows can determine
        k_s = min(k_als, n_s * geometry.n_cam)
        sel = random_swap(US[:, :k_s], n_s, groups=groups_l, max_steps=config.sampling_steps, seed=seed + n_thesis)
        rows = _rows_of_groups(np.asarray(sel.units), geometry, geometry.n_leds)
        pairs = np.stack(np.divmod(np.asarray(sel.units, dtype=np.int64), geometry.n_leds), axis=1)
        sampling["paper4"]["counts"][str(n_thesis)] = {"n_s": n_s, "n_meas": int(len(rows)),
                                                       "kappa": sel.kappa, "pairs": pairs.tolist()}
        tik = solve_operator(Ua, sa, method="tikhonov", rows=rows, lam=LAMBDA_ALS, fused=False)
        strategies.append(Strategy(f"sparse-tikhonov-n{n_thesis}", "linear", "single", rows, {"rgb": tik},
                                   {"paper": "4", "lam": LAMBDA_ALS, "n_s": n_s, "k": k_als,
                                    "n_meas": int(len(rows)), "condition": tik.condition}))
        k_p = min(k_als, len(rows))
        pinv = solve_operator(Ua[:, :k_p], method="pinv", rows=rows, fused=False)
        strategies.append(Strategy(f"sparse-pinv-n{n_thesis}", "linear", "single", rows, {"rgb": pinv},
                                   {"paper": "1 eq. 3", "n_s": n_s, "k": k_p, "n_meas": int(len(rows)),
                                    "condition": pinv.condition}))
    mux = solve_operator(Ua, sa, method="direct", patterns=patterns, lam=LAMBDA_ALS, fused=False)
    strategies.append(Strategy("multiplexed-direct", "linear", "mux", None, {"rgb": mux},
                               {"paper": "4 eq. 10", "lam": LAMBDA_ALS, "k": k_als,
                                "n_meas": int(geometry.n_views * patterns.shape[0]), "condition": mux.condition}))
    n_p = patterns.shape[0]
    n_s = scaled_pairs(THESIS_N_S[-1], geometry.n_turn * n_p)
    A = multiplexed_basis(patterns, Ua, sa)
    sel = random_swap(A[:, :min(k_als, n_s * geometry.n_cam)], n_s, groups=_groups(geometry, n_p),
                      max_steps=config.sampling_steps, seed=seed + 1)
    rows = _rows_of_groups(np.asarray(sel.units), geometry, n_p)
    pairs = np.stack(np.divmod(np.asarray(sel.units, dtype=np.int64), n_p), axis=1)
    sm = solve_operator(Ua, sa, method="direct", patterns=patterns, rows=rows, lam=LAMBDA_ALS, fused=False)
    sampling["paper4"]["sparse_multiplexed"] = {"n_s": n_s, "n_meas": int(len(rows)), "kappa": sel.kappa,
                                                "pairs": pairs.tolist()}
    strategies.append(Strategy(f"sparse-multiplexed-n{THESIS_N_S[-1]}", "linear", "mux", rows, {"rgb": sm},
                               {"paper": "4 eq. 10", "lam": LAMBDA_ALS, "n_s": n_s, "k": k_als,
                                "n_meas": int(len(rows)), "condition": sm.condition}))
    return strategies, sampling


# --------------------------------------------------------------------------- measurement simulation per band


def multiplex(truth: np.ndarray, patterns: np.ndarray, geometry: Geometry) -> np.ndarray:
    """Multiplexed images ``(n_views * n_p, ...)``: each view's LED images summed by every pattern.

    Light superposes, so the multiplexed radiance is formed from the linear,
    noise-free truth; the noise comes afterwards (DESIGN §4).
    """
    n_p = patterns.shape[0]
    tail = truth.shape[1:]
    t = truth.reshape(geometry.n_views, geometry.n_leds, -1)
    out = np.matmul(patterns.astype(np.float32)[None], t)                    # (I_views (x) M) B
    return out.reshape((geometry.n_views * n_p,) + tail)


def demultiplex_views(measured: np.ndarray, patterns: np.ndarray, geometry: Geometry,
                      P: np.ndarray | None = None) -> np.ndarray:
    """Least-squares demultiplexing of every view (VMV §3.2): ``(n_lv, ...)``."""
    P = demultiplex_operator(patterns) if P is None else P
    tail = measured.shape[1:]
    m = measured.reshape(geometry.n_views, patterns.shape[0], -1)
    return np.matmul(P.astype(np.float32)[None], m).reshape((geometry.n_lv,) + tail)


def _read_rows(path: str, r0: int, r1: int) -> np.ndarray:
    return np.asarray(zarr.open_group(path, mode="r", zarr_format=3)["btf"][:, r0:r1], dtype=np.float32)


def band_maxima(path: str, r0: int, r1: int, patterns: np.ndarray, geometry: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Brightest noise-free value of every single-light and multiplexed image within texture rows r0:r1."""
    truth = _read_rows(path, r0, r1)
    n = truth.shape[0]
    return truth.reshape(n, -1).max(axis=1), multiplex(truth, patterns, geometry).reshape(-1, truth[0].size).max(axis=1)


def _expose_rows(signal: np.ndarray, r0: int, gain: np.ndarray, noise: SensorNoise, seed: Sequence[int],
                 kind: int) -> np.ndarray:
    """Noisy ``signal`` (texture rows ``r0 : r0 + len`` on axis 1); row ``r``'s noise comes from ``seed + [kind, r]``."""
    out = np.empty_like(signal)
    for i in range(signal.shape[1]):
        out[:, i] = expose(signal[:, i], gain, noise, np.random.default_rng([*seed, kind, r0 + i]))
    return out


def noisy_single(truth: np.ndarray, r0: int, gains: tuple[np.ndarray, np.ndarray], noise: SensorNoise,
                 seed: Sequence[int]) -> np.ndarray:
    """Noisy single-light measurement of texture rows ``r0 : r0 + len``."""
    return _expose_rows(truth, r0, gains[0], noise, seed, 0)


def noisy_multiplexed(truth: np.ndarray, r0: int, gains: tuple[np.ndarray, np.ndarray], patterns: np.ndarray,
                      geometry: Geometry, noise: SensorNoise, seed: Sequence[int]) -> np.ndarray:
    """Noisy multiplexed measurement (every view under every pattern) of texture rows ``r0 : r0 + len``."""
    return _expose_rows(multiplex(truth, patterns, geometry), r0, gains[1], noise, seed, 1)


def noisy_rows(truth: np.ndarray, r0: int, gains: tuple[np.ndarray, np.ndarray], patterns: np.ndarray,
               geometry: Geometry, noise: SensorNoise, seed: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Noisy single-light and multiplexed measurements of texture rows ``r0 : r0 + len``.

    The noise of texture row ``r`` is drawn from its own generator
    (``seed + [kind, r]``), so a row is measured alike in every band and halo
    that contains it.
    """
    return (noisy_single(truth, r0, gains, noise, seed),
            noisy_multiplexed(truth, r0, gains, patterns, geometry, noise, seed))


def _chan(a: tuple[np.ndarray, np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray, np.ndarray]):
    """Chan et al.'s pairwise combination of (count, mean, M2)."""
    na, ma, qa = a
    nb, mb, qb = b
    n = na + nb
    d = mb - ma
    return n, ma + d * nb / n, qa + qb + d * d * na * nb / n


def band_variance(path: str, r0: int, r1: int, gains: tuple[np.ndarray, np.ndarray], patterns: np.ndarray,
                  geometry: Geometry, noise: SensorNoise, seed: Sequence[int]) -> tuple[np.ndarray, ...]:
    """(count, mean, M2) per row of the linear demultiplexed RGB (texels and channels) within rows r0:r1."""
    truth = _read_rows(path, r0, r1)
    mux = noisy_multiplexed(truth, r0, gains, patterns, geometry, noise, seed)
    x = demultiplex_views(mux, patterns, geometry).astype(np.float64).reshape(geometry.n_lv, -1)   # (n_lv, m)
    m = x.shape[1]
    mean = x.mean(axis=1)
    return np.float64(m), mean, ((x - mean[:, None]) ** 2).sum(axis=1)


@dataclass
class BandScores:
    """Error sums of one strategy over some texels, reduced over bands."""

    sse_log_y: float = 0.0
    ss_log_y: float = 0.0
    sse_rows: np.ndarray | None = None      # (n_lv,) per-texture squared error, linear RGB
    ss_rows: np.ndarray | None = None       # (n_lv,) per-texture squared norm of the truth
    n_texels: int = 0

    def add(self, other: "BandScores") -> "BandScores":
        if self.sse_rows is None:
            return other
        return BandScores(self.sse_log_y + other.sse_log_y, self.ss_log_y + other.ss_log_y,
                          self.sse_rows + other.sse_rows, self.ss_rows + other.ss_rows,
                          self.n_texels + other.n_texels)


@dataclass(frozen=True)
class BandTruth:
    """The truth's terms of :func:`score_band`, computed once per band for every strategy."""

    rgb: np.ndarray            # (n_lv, rows, w, 3) linear RGB
    log_y: np.ndarray          # (n_lv, rows, w) float64 log Y
    ss_rows: np.ndarray        # (n_lv,) squared norm of each texture

    @classmethod
    def of(cls, truth: np.ndarray) -> "BandTruth":
        t = truth.reshape(truth.shape[0], -1).astype(np.float64)
        return cls(truth, log_luminance(truth).astype(np.float64), np.einsum("ij,ij->i", t, t))


def score_band(ref: BandTruth, recon: np.ndarray) -> BandScores:
    """Sums for relative L2 on log Y and the per-texture errors of mRMSE / mPSNR / mRE."""
    t = ref.rgb
    d = (recon.astype(np.float64) - t).reshape(t.shape[0], -1)
    e = log_luminance(recon).astype(np.float64) - ref.log_y
    return BandScores(float(np.vdot(e, e)), float(np.vdot(ref.log_y, ref.log_y)), np.einsum("ij,ij->i", d, d),
                      ref.ss_rows, int(t.shape[1] * t.shape[2]))


def finish_scores(s: BandScores, row_max: np.ndarray) -> dict[str, float]:
    """Relative L2 on log Y (paper 1 §4.1.1) and SR eqs. (8)-(10) from the band sums.

    Equal to :func:`btfcore.metrics.relative_error` (``space='log_y'``),
    :func:`~btfcore.metrics.mrmse`, :func:`~btfcore.metrics.mpsnr` and
    :func:`~btfcore.metrics.mre` of the whole BTF (tested).
    """
    rmse = np.sqrt(s.sse_rows) / np.sqrt(s.n_texels)                          # eq. (8) term
    with np.errstate(divide="ignore"):
        psnr = 20 * np.log10(row_max / rmse)                                 # eq. (9) term
    return {"rel_l2_log_y": float(np.sqrt(s.sse_log_y / s.ss_log_y)), "mrmse": float(np.mean(rmse)),
            "mpsnr": float(np.mean(psnr)), "mre": float(np.mean(np.sqrt(s.sse_rows / s.ss_rows)) * 100)}


def reconstruct_band(strategy: Strategy, r0: int, r1: int, height: int, truth_halo: np.ndarray,
                     single_halo: np.ndarray, mux: np.ndarray, g0: int, geometry: Geometry,
                     demux: np.ndarray, log_cache: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """One strategy's reconstruction of texture rows r0:r1, linear RGB ``(n_lv, r1 - r0, w, 3)``.

    ``truth_halo`` and ``single_halo`` hold texture rows ``g0 : g0 + len`` (the ABTF halo);
    ``mux`` (the multiplexed measurement) and ``demux`` (it demultiplexed) rows r0:r1 only.
    ``log_cache`` keeps the log-space conversion of a whole source between the strategies of a band.
    """
    log_cache = {} if log_cache is None else log_cache
    a, b = r0 - g0, r1 - g0
    n_lv, w = geometry.n_lv, geometry.width
    if strategy.space == "linear":
        op = strategy.operators["rgb"]
        if strategy.source == "single":
            y = single_halo[strategy.rows, a:b]
        elif strategy.source == "demux":
            y = demux
        else:
            y = mux if strategy.rows is None else mux[strategy.rows]
        out = apply(op, y.reshape(y.shape[0], -1))
        return out.reshape(n_lv, r1 - r0, w, 3)
    if strategy.source == "demux":
        if not strategy.operators:
            return np.maximum(demux, 0.0)                                  # plain demultiplexing
        x_band = to_log_yuv(demux)
        x = np.stack([apply(strategy.operators[c], x_band[..., i].reshape(n_lv, -1)).reshape(n_lv, r1 - r0, w)
                      for i, c in enumerate(CHANNELS)], axis=-1)
        return _to_rgb(x)
    source = truth_halo if strategy.source == "truth" else single_halo
    if strategy.rows is None or len(strategy.rows) == len(source):
        if strategy.source not in log_cache:                                   # every row: convert once per band
            log_cache[strategy.source] = to_log_yuv(source)
        x_all = log_cache[strategy.source]
        x_all = x_all if strategy.rows is None else x_all[strategy.rows]
    else:
        x_all = to_log_yuv(source[strategy.rows])                              # (n_meas, halo rows, w, 3)
    chans = []
    for i, c in enumerate(CHANNELS):
        op = strategy.operators[c]
        if op.patch_size is not None:                                          # ABTF: band with its halo
            chans.append(reconstruct_abtf(op, x_all[..., i], out_rows=(r0, r1), height=height))
        else:
            chans.append(apply(op, x_all[:, a:b, :, i].reshape(x_all.shape[0], -1)).reshape(n_lv, r1 - r0, w))
    return _to_rgb(np.stack(chans, axis=-1))


#: Range a log-space reconstruction is clipped to before it is mapped back to RGB: log Y in
#: [log eps, LOG_Y_MAX] (an unregularised solve can extrapolate to exp overflow), U/Y and V/Y in
#: [-CHROMA_MAX, CHROMA_MAX]. Far outside any truth value, so the errors stay those of the solve.
LOG_Y_MAX = 20.0
CHROMA_MAX = 5.0


def _to_rgb(x: np.ndarray) -> np.ndarray:
    """``from_log_yuv`` of a log-space reconstruction clipped to :data:`LOG_Y_MAX` / :data:`CHROMA_MAX`."""
    from btfcore.model.colour import LOG_YUV_EPS

    x = np.array(x, dtype=np.float32)
    np.clip(x[..., 0], np.log(LOG_YUV_EPS), LOG_Y_MAX, out=x[..., 0])
    np.clip(x[..., 1:], -CHROMA_MAX, CHROMA_MAX, out=x[..., 1:])
    return from_log_yuv(x)


def evaluate_band(path: str, r0: int, r1: int, strategies: list[Strategy], gains: tuple[np.ndarray, np.ndarray],
                  patterns: np.ndarray, geometry: Geometry, noise: SensorNoise, seed: Sequence[int],
                  write: dict[str, str] | None = None) -> dict[str, BandScores]:
    """Measure, reconstruct and score every strategy on texture rows r0:r1 (one Dask task).

    With ``write`` (``{strategy: store path}``) the reconstructions are also
    written to those stores (this band owns whole chunks of them).
    """
    h = geometry.height
    halo = abtf_halo(r0, r1, h, 3) if h >= 3 else slice(r0, r1)
    g0 = halo.start
    truth_halo = _read_rows(path, halo.start, halo.stop)
    single = noisy_single(truth_halo, g0, gains, noise, seed)
    truth = truth_halo[:, r0 - g0:r1 - g0]
    mux = noisy_multiplexed(truth, r0, gains, patterns, geometry, noise, seed)   # each row's noise is the row's own
    demux = demultiplex_views(mux, patterns, geometry)
    scores, ref, log_cache = {}, BandTruth.of(truth), {}
    for strategy in strategies:
        recon = reconstruct_band(strategy, r0, r1, h, truth_halo, single, mux, g0, geometry, demux, log_cache)
        recon = np.asarray(recon, dtype=np.float32)
        if not np.all(np.isfinite(recon)):
            bad = np.unravel_index(int(np.argmin(np.isfinite(recon))), recon.shape)
            raise ValueError(f"{path}: strategy {strategy.name} produced a non-finite value at "
                             f"(row {bad[0]}, texel {r0 + bad[1]}, {bad[2]}); check its operator's condition")
        scores[strategy.name] = score_band(ref, recon)
        if write and strategy.name in write:
            zarr.open_group(write[strategy.name], mode="r+", zarr_format=3)["btf"][:, r0:r1] = recon
    return scores


# --------------------------------------------------------------------------- the whole evaluation


def bands(height: int, band_rows: int) -> list[tuple[int, int]]:
    """Bands of texture rows, the unit of parallel work (and of the reconstruction stores' chunks)."""
    return [(r, min(r + band_rows, height)) for r in range(0, height, band_rows)]


def _material_index(material_id: str) -> int:
    return int(hashlib.sha256(material_id.encode()).hexdigest()[:8], 16)


def _reduce_max(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    return np.max([p[0] for p in parts], axis=0), np.max([p[1] for p in parts], axis=0)


def _gains(maxima: tuple[np.ndarray, np.ndarray], noise: SensorNoise, path: str) -> tuple[np.ndarray, np.ndarray]:
    try:
        return exposure_gain(maxima[0], noise), exposure_gain(maxima[1], noise)
    except ValueError as exc:
        raise ValueError(f"{path}: btf: {exc}") from None


def _reduce_variance(parts: list[tuple]) -> np.ndarray:
    acc = parts[0]
    for p in parts[1:]:
        acc = _chan(acc, p)
    n, _, m2 = acc
    return m2 / n                                                    # population variance per row


def _operators(model_path: str, materials: list[Material], material_id: str, settings: ModelSettings,
               geometry: Geometry, config: EvaluationConfig, variance: np.ndarray, patterns: np.ndarray
               ) -> tuple[list[Strategy], dict[str, Any]]:
    material = next(m for m in materials if m.material_id == material_id)
    bases = leave_one_out_bases(model_path, materials, material_id, settings)
    group = zarr.open_group(material.path, mode="r", zarr_format=3)
    return build_strategies(bases, geometry, np.asarray(group["light_dir"][...]), np.asarray(group["view_dir"][...]),
                            config, variance, patterns, config.seed + _material_index(material_id) % 100000)


def _first(pair: tuple) -> Any:
    return pair[0]


def _strategy_info(pair: tuple[list[Strategy], dict[str, Any]]) -> tuple[dict[str, Any], dict[str, Any]]:
    """The reportable part of the operators (not the operators themselves)."""
    return {s.name: s.info for s in pair[0]}, pair[1]


def _reduce_scores(parts: list[dict[str, BandScores]]) -> dict[str, BandScores]:
    out: dict[str, BandScores] = {}
    for part in parts:
        for name, s in part.items():
            out[name] = out.get(name, BandScores()).add(s)
    return out


def _geometry(material: Material) -> Geometry:
    attrs = dict(zarr.open_group(material.path, mode="r", zarr_format=3).attrs)
    tcl = attrs.get("turntable_cameras_leds")
    if not tcl or int(np.prod(tcl)) != material.n_lv:
        raise ValueError(f"{material.path}: attribute turntable_cameras_leds is {tcl!r}, which does not give its "
                         f"{material.n_lv} light/view pairs; the evaluation needs the (turntable, camera, light) "
                         "layout to simulate multiplexed shots (write the store with ensure_truth_database)")
    return Geometry(int(tcl[0]), int(tcl[1]), int(tcl[2]), *material.texture_shape)


def create_reconstruction_store(path: Path, truth_path: str, band_rows: int, strategy: str) -> str:
    """An empty ``btf-texture`` store for one strategy's reconstruction (chunks = bands), directions copied."""
    src = zarr.open_group(truth_path, mode="r", zarr_format=3)
    n_lv, h, w, _ = src["btf"].shape
    group = begin_store(path)
    create_array(group, "btf", shape=(n_lv, h, w, 3), chunks=(n_lv, band_rows, w, 3), dtype="float32",
                       fill_value=0.0, compressors=None, dimension_names=["lv", "tex_row", "tex_col", "channel"])
    for name in ("light_dir", "view_dir"):
        data = src[name][...]
        create_array(group, name, shape=data.shape, dtype=data.dtype, chunks=data.shape, compressors=None)[...] = data
    group.attrs.put(to_json_attr({"schema": "btf-texture", "schema_version": "1.0", "complete": False,
                                  "texture_shape": [h, w], "reconstruction_of": truth_path, "strategy": strategy,
                                  "ingest_hash": f"reconstruction-{strategy}"}))
    finish_store(path, group)
    return str(path)


def evaluate_materials(model_path: str, materials: list[Material], config: EvaluationConfig, client: Any,
                       out_dir: str | os.PathLike, *, render_ids: Sequence[str] = (),
                       progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Every strategy on every held-out material: one Dask graph of (material, band) tasks.

    Per material: band maxima -> exposure gains -> band variances of the
    demultiplexed measurement -> operators (leave-one-out bases, samplings) ->
    band reconstructions and error sums -> scores. Materials in
    ``render_ids`` also get their reconstructions written to
    ``out_dir/reconstructions/<material>/<strategy>.zarr``.

    Returns
    -------
    result : dict
        ``{"materials": {id: {"class", "scores": {strategy: metrics}, "strategies": {strategy: info},
        "sampling": ...}}, "reconstructions": {id: {strategy: path}}}``.
    """
    from distributed import as_completed

    settings = config.model_settings()
    device_noise = config.build_device().sensor
    noise = SensorNoise(float(device_noise.full_well_e), float(device_noise.read_noise_e), config.fill)
    out_dir = Path(out_dir)
    finals, stores = {}, {}
    for m in materials:
        geometry = _geometry(m)
        patterns = multiplexing_patterns(geometry.n_leds)
        seed = (config.seed, _material_index(m.material_id) % (1 << 31))
        parts = bands(geometry.height, config.band_rows)
        maxima = client.submit(_reduce_max, [client.submit(band_maxima, m.path, r0, r1, patterns, geometry,
                                                           pure=False) for r0, r1 in parts], pure=False)
        gains = client.submit(_gains, maxima, noise, m.path, pure=False)
        variance = client.submit(_reduce_variance, [client.submit(band_variance, m.path, r0, r1, gains, patterns,
                                                                  geometry, noise, seed, pure=False)
                                                    for r0, r1 in parts], pure=False)
        ops = client.submit(_operators, model_path, materials, m.material_id, settings, geometry, config, variance,
                            patterns, pure=False)
        strategies = client.submit(_first, ops, pure=False)
        info = client.submit(_strategy_info, ops, pure=False)
        write = None
        if m.material_id in render_ids:
            folder = out_dir / "reconstructions" / m.material_id
            folder.mkdir(parents=True, exist_ok=True)
            write = {name: create_reconstruction_store(folder / f"{name}.zarr", m.path, config.band_rows, name)
                     for name in strategy_names()}
            stores[m.material_id] = write
        scores = client.submit(_reduce_scores, [client.submit(evaluate_band, m.path, r0, r1, strategies, gains,
                                                              patterns, geometry, noise, seed, write, pure=False)
                                                for r0, r1 in parts], pure=False)
        finals[m.material_id] = (scores, info, maxima)
    flat = [f for trio in finals.values() for f in trio]
    for done, future in enumerate(as_completed(flat), 1):
        future.result()
        if progress is not None:
            progress(done, len(flat))
    result: dict[str, Any] = {"materials": {}, "reconstructions": stores}
    for m in materials:
        scores_f, ops_f, maxima_f = finals[m.material_id]
        scores, (info, sampling), maxima = scores_f.result(), ops_f.result(), maxima_f.result()
        result["materials"][m.material_id] = {
            "class": m.cls,
            "scores": {name: finish_scores(s, maxima[0]) for name, s in scores.items()},
            "strategies": info, "sampling": sampling}
    for material_stores in stores.values():
        for path in material_stores.values():
            zarr.open_group(path, mode="r+", zarr_format=3).attrs.update({"complete": True})
    return result


def strategy_names() -> list[str]:
    """Names of the strategies :func:`build_strategies` makes, in its order."""
    names = [f"{model}-{s}" for s in ("pmap7", "optimized") for model in ("abrdf", "abtf")]
    names += ["abrdf-projection", "abtf-projection", "demultiplexed", "projection", "thresholded"]
    for n in THESIS_N_S:
        names += [f"sparse-tikhonov-n{n}", f"sparse-pinv-n{n}"]
    return names + ["multiplexed-direct", f"sparse-multiplexed-n{THESIS_N_S[-1]}"]


# --------------------------------------------------------------------------- tables and claims


def class_means(result: dict[str, Any], metric: str = "rel_l2_log_y") -> dict[str, dict[str, float]]:
    """``{class: {strategy: mean of metric over the class' materials}}`` (errors in the metric's unit)."""
    by_class: dict[str, list[dict[str, Any]]] = {}
    for rec in result["materials"].values():
        by_class.setdefault(rec["class"], []).append(rec["scores"])
    return {cls: {name: float(np.mean([s[name][metric] for s in recs])) for name in recs[0]}
            for cls, recs in sorted(by_class.items())}


def overall_means(result: dict[str, Any], metric: str = "rel_l2_log_y") -> dict[str, float]:
    recs = [rec["scores"] for rec in result["materials"].values()]
    return {name: float(np.mean([s[name][metric] for s in recs])) for name in recs[0]}


def predicted_times(device: Device, sampling: dict[str, Any]) -> dict[str, Any]:
    """Predicted acquisition times (btfcore.acquisition.time_model) of the plans of the paper-4 strategies.

    On the evaluated device (its turntable positions) and on the thesis' full
    dome (12 positions, the thesis' n_s = 400 pairs drawn at random: the time
    depends on the count, not on which pairs).
    """
    from btfcore.acquisition.plan import full_single_light_plan, multiplexed_plan, sparse_multiplexed_plan, sparse_plan
    from btfcore.acquisition.time_model import predict_time

    p4 = sampling["paper4"]
    n400 = str(THESIS_N_S[-1])
    here = {
        "full-single": predict_time(full_single_light_plan(device)).total_s,
        "sparse": predict_time(sparse_plan(device, np.asarray(p4["counts"][n400]["pairs"]))).total_s,
        "multiplexed": predict_time(multiplexed_plan(device)).total_s,
        "sparse-multiplexed": predict_time(sparse_multiplexed_plan(
            device, np.asarray(p4["sparse_multiplexed"]["pairs"]))).total_s,
    }
    full = get_device("bonn-dome2")
    rng = np.random.default_rng(0)
    n_p = multiplexing_patterns(full.n_leds).shape[0]

    def draw(n_cols: int) -> np.ndarray:
        flat = np.sort(rng.choice(full.n_turn * n_cols, size=THESIS_N_S[-1], replace=False))
        return np.stack(np.divmod(flat, n_cols), axis=1)

    thesis = {
        "full-single": predict_time(full_single_light_plan(full)).total_s,
        "sparse": predict_time(sparse_plan(full, draw(full.n_leds))).total_s,
        "multiplexed": predict_time(multiplexed_plan(full)).total_s,
        "sparse-multiplexed": predict_time(sparse_multiplexed_plan(full, draw(n_p))).total_s,
    }
    return {"evaluated_device_s": here, "thesis_device_s": thesis,
            "exposure": "btfcore.acquisition.plan.ExposureModel() defaults: single-light bracket 10, 100, 1000 ms; a pattern "
                        "of m LEDs 1/m of it", "params": "btfcore.acquisition.time_model.TimeModelParams() defaults"}


def _verdict(ok: bool) -> str:
    return "met" if ok else "not met"


def claims(result: dict[str, Any], times: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The thesis' claims (a)-(e) with their numbers and a verdict computed from them."""
    cm = class_means(result)
    om = overall_means(result)
    out: dict[str, dict[str, Any]] = {}

    rows = {cls: {k: round(100 * cm[cls][k], 3) for k in ("abrdf-pmap7", "abrdf-optimized", "abtf-pmap7",
                                                           "abtf-optimized")} for cls in STRUCTURED_CLASSES if cls in cm}
    ok = bool(rows) and all(r["abtf-optimized"] < r["abrdf-optimized"] and r["abtf-pmap7"] < r["abrdf-pmap7"]
                            for r in rows.values())
    out["a"] = {"claim": "With about 6% of the samples, ABTF-patch reconstruction beats ABRDF reconstruction on "
                         "carpet, stone and leather (paper 1 Table 2), log Y relative L2 [%]",
                "numbers": rows, "rule": "ABTF < ABRDF for both samplings in every listed class",
                "verdict": _verdict(ok) if rows else "not tested (no structured class in the database)"}

    per_mat = [rec["scores"] for rec in result["materials"].values()]
    nums = {}
    ok = True
    for model in ("abrdf", "abtf"):
        o, p = om[f"{model}-optimized"], om[f"{model}-pmap7"]
        wins = sum(s[f"{model}-optimized"]["rel_l2_log_y"] < s[f"{model}-pmap7"]["rel_l2_log_y"] for s in per_mat)
        nums[model] = {"optimized": round(100 * o, 3), "pmap7": round(100 * p, 3),
                       "materials_where_optimized_wins": f"{wins}/{len(per_mat)}"}
        ok = ok and o < p
    out["b"] = {"claim": "Optimised sampling (random swap, paper 1 Alg. 1) beats the 7x7 parabolic map at the same "
                         "number of samples, mean log Y relative L2 [%] over all materials",
                "numbers": nums, "rule": "mean(optimized) < mean(pmap7) for ABRDF and ABTF bases",
                "verdict": _verdict(ok)}

    rows = {cls: {k: round(100 * cm[cls][k], 3) for k in ("demultiplexed", "projection", "thresholded")} for cls in cm}
    rows["all"] = {k: round(100 * om[k], 3) for k in ("demultiplexed", "projection", "thresholded")}
    a = rows["all"]
    classes = [r for k, r in rows.items() if k != "all"]
    rows["halves"] = {f"{lo} < {hi}": {"means": _verdict(a[lo] < a[hi]),
                                       "classes": f"{sum(r[lo] < r[hi] for r in classes)}/{len(classes)}"}
                      for lo, hi in (("projection", "demultiplexed"), ("thresholded", "projection"))}
    out["c"] = {"claim": "Thresholded de-noising beats projection de-noising, which beats plain demultiplexing "
                         "(VMV Table 1), log Y relative L2 [%]", "numbers": rows,
                "rule": "thresholded < projection < demultiplexed, means over all materials",
                "classes_in_order": f"{sum(r['thresholded'] < r['projection'] < r['demultiplexed'] for r in classes)}/{len(cm)}",
                "verdict": _verdict(a["thresholded"] < a["projection"] < a["demultiplexed"])}

    n = THESIS_N_S[-1]
    e_sm, e_s, e_m = om[f"sparse-multiplexed-n{n}"], om[f"sparse-tikhonov-n{n}"], om["multiplexed-direct"]
    t = times["evaluated_device_s"]
    ok = e_sm <= 2 * e_s and e_sm <= 2 * e_m and t["sparse-multiplexed"] < min(t["sparse"], t["multiplexed"])
    out["d"] = {"claim": f"Sparse + multiplexed with n_s = {n} of 2,376 (light, turntable) pairs (scaled to the "
                         "evaluated device), all cameras, has an error within 2x of sparse-only and of "
                         "multiplexed-only at a fraction of their predicted acquisition time (paper 4 §5.3)",
                "numbers": {"rel_l2_log_y_percent": {"sparse-multiplexed": round(100 * e_sm, 3),
                                                     "sparse-only (Tikhonov)": round(100 * e_s, 3),
                                                     "multiplexed-only (eq. 10)": round(100 * e_m, 3)},
                            "ratio_to_sparse": round(e_sm / e_s, 3), "ratio_to_multiplexed": round(e_sm / e_m, 3),
                            "predicted_time_s_evaluated_device": {k: round(v, 1) for k, v in t.items()},
                            "predicted_time_h_thesis_device": {k: round(v / 3600, 3)
                                                               for k, v in times["thesis_device_s"].items()}},
                "rule": "error <= 2x both, and predicted time < both (evaluated device)",
                "verdict": _verdict(ok)}

    n0 = THESIS_N_S[0]
    tik, pinv = om[f"sparse-tikhonov-n{n0}"], om[f"sparse-pinv-n{n0}"]
    nums = {f"n_s={n_}": {"tikhonov": round(100 * om[f"sparse-tikhonov-n{n_}"], 3),
                          "pinv": round(100 * om[f"sparse-pinv-n{n_}"], 3)} for n_ in THESIS_N_S}
    out["e"] = {"claim": f"Tikhonov with lambda*Sigma^-1 (lambda = {LAMBDA_ALS}, ALS basis) beats the unregularised "
                         "pseudo-inverse at the smallest sample count, mean log Y relative L2 [%] (thesis n_s scaled)",
                "numbers": nums, "rule": f"tikhonov < pinv at the thesis' n_s = {n0} (scaled)",
                "verdict": _verdict(tik < pinv)}
    return out


def thesis_tables(result: dict[str, Any]) -> dict[str, Any]:
    """Tables shaped like the thesis': paper 1 Table 2, VMV Table 1 and paper 4's comparison (percent)."""
    cm = class_means(result)
    t2 = [["class", "ABRDF proj", "ABRDF pmap7", "ABRDF optimized", "ABTF proj", "ABTF pmap7", "ABTF optimized"]]
    for cls, row in cm.items():
        t2.append([cls] + [round(100 * row[k], 2) for k in ("abrdf-projection", "abrdf-pmap7", "abrdf-optimized",
                                                            "abtf-projection", "abtf-pmap7", "abtf-optimized")])
    t1 = [["material", "class", "eps_demult", "eps_denoised", "eps_threshold"]]
    for mid, rec in result["materials"].items():
        t1.append([mid, rec["class"]] + [round(100 * rec["scores"][k]["rel_l2_log_y"], 2)
                                         for k in ("demultiplexed", "projection", "thresholded")])
    for cls, row in cm.items():
        t1.append([f"mean {cls}", cls] + [round(100 * row[k], 2) for k in ("demultiplexed", "projection", "thresholded")])
    om = {m: overall_means(result, m) for m in ("rel_l2_log_y", "mrmse", "mpsnr", "mre")}
    t4 = [["strategy", "rel. L2 log Y [%]", "mRMSE", "mPSNR [dB]", "mRE [%]"]]
    for name in om["rel_l2_log_y"]:
        t4.append([name, round(100 * om["rel_l2_log_y"][name], 2), float(f"{om['mrmse'][name]:.4g}"),
                   round(om["mpsnr"][name], 2), round(om["mre"][name], 2)])
    return {"paper1_table2": t2, "vmv_table1": t1, "all_strategies": t4}


# --------------------------------------------------------------------------- renderings and report


def env_map_path() -> str | None:
    """The shared environment map (``env/forest.exr``), or None where the shared data is absent."""
    from tasks.shared_data import shared_file

    path = shared_file("env/forest.exr")
    return None if path is None else str(path)


def render_one(store: str, out_png: str, size: int, env: str | None, white: float | None) -> dict[str, Any]:
    """Render one BTF store on a sphere (point light, or environment map when ``env``); image and mask."""
    from tasks.render import render_store

    r = render_store(store, "sphere", env=env, out_png=out_png, image_size=size, white=white,
                     env_lights_shape=(6, 12))
    return {"image": r.image, "mask": r.mask, "png": Path(out_png).name}


def renderings(truth_path: str, stores: dict[str, str], out_dir: str | os.PathLike, size: int, client: Any
               ) -> dict[str, Any]:
    """Sphere renderings of the truth and every reconstruction under a point light (and the environment
    map when present), one Dask task each, with the PSNR of each against the truth's rendering."""
    from btfcore.metrics import psnr

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    env = env_map_path()
    lights = {"point": None} | ({"env": env} if env else {})
    result: dict[str, Any] = {"lights": list(lights), "env_map": env, "images": {}, "psnr_db": {}}
    for light, env_path in lights.items():
        truth = client.submit(render_one, truth_path, str(out / f"render_{light}_truth.png"), size, env_path, None,
                              pure=False).result()
        covered = truth["image"][truth["mask"]]
        white = float(np.percentile(covered[covered > 0], 99.5)) if np.any(covered > 0) else None
        # the truth's PNG again with the common white point, so that all images compare
        truth = client.submit(render_one, truth_path, str(out / f"render_{light}_truth.png"), size, env_path, white,
                              pure=False).result()
        futures = {name: client.submit(render_one, path, str(out / f"render_{light}_{name}.png"), size, env_path,
                                       white, pure=False) for name, path in stores.items()}
        result["images"][light] = {"truth": truth["png"]}
        result["psnr_db"][light] = {}
        peak = float(truth["image"][truth["mask"]].max())
        for name, future in futures.items():
            r = future.result()
            result["images"][light][name] = r["png"]
            result["psnr_db"][light][name] = round(psnr(truth["image"][truth["mask"]], r["image"][truth["mask"]],
                                                        peak=peak), 3)
    return result


def abrdf_images(truth_path: str, stores: dict[str, str], geometry: Geometry, out_dir: str | os.PathLike
                 ) -> dict[str, str]:
    """The centre texel's ABRDF (rows: views, columns: lights) of the truth and every reconstruction, PNG,
    tone-mapped with the truth's white point."""
    from btfcore.render.tonemap import tonemap
    from tasks.report import save_png

    out = Path(out_dir)
    h, w = geometry.height // 2, geometry.width // 2

    def column(path: str) -> np.ndarray:
        col = np.asarray(zarr.open_group(path, mode="r", zarr_format=3)["btf"][:, h, w, :], dtype=np.float64)
        return np.maximum(col.reshape(geometry.n_views, geometry.n_leds, 3), 0.0)

    truth = column(truth_path)
    white = float(np.percentile(truth, 99.5)) or 1.0
    scale = (max(1, 96 // geometry.n_views), max(1, 384 // geometry.n_leds))
    files = {"truth": save_png(out / "abrdf_truth.png", tonemap(truth, white=white), scale=scale)}
    for name, path in stores.items():
        files[name] = save_png(out / f"abrdf_{name}.png", tonemap(column(path), white=white), scale=scale)
    return files


def scale_of(materials: Sequence[Material], geometry: Geometry, config: EvaluationConfig) -> dict[str, Any]:
    """What the evaluation ran on, for the report."""
    n_pairs = geometry.n_turn * geometry.n_leds
    n_p = multiplexing_patterns(geometry.n_leds).shape[0]
    return {"device": config.device, "turntable_positions": geometry.n_turn, "cameras": geometry.n_cam,
            "leds": geometry.n_leds, "light_view_pairs": geometry.n_lv,
            "texture": [geometry.height, geometry.width], "materials": len(materials),
            "classes": sorted({m.cls for m in materials}),
            "materials_per_class": {c: sum(m.cls == c for m in materials) for c in sorted({m.cls for m in materials})},
            "light_turntable_pairs": n_pairs, "s_matrix_order": int(n_p),
            "thesis_n_s_scaled": {str(n): scaled_pairs(n, n_pairs) for n in THESIS_N_S},
            "sparse_multiplexed_n_s": scaled_pairs(THESIS_N_S[-1], geometry.n_turn * n_p),
            "note": f"thesis: 26,136 pairs (12 turntable positions); n_s scaled by {n_pairs}/{THESIS_PAIRS}"}


def evaluate_acquisition(db: str | os.PathLike, out_dir: str | os.PathLike, client: Any,
                         config: EvaluationConfig = EvaluationConfig(), *,
                         progress: Callable[[str], Callable[[int, int], None] | None] | None = None
                         ) -> dict[str, Any]:
    """Truth database, leave-one-out bases, every strategy on every material, renderings: the summary.

    ``progress(stage)`` may return a ``(done, total)`` callback per stage.
    The report is written by :func:`write_acquisition_report`.
    """
    start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    ensure_truth_database(config, db, client, progress=progress and progress("truth BTFs"))
    materials = discover(db)
    seconds["truth"] = time.perf_counter() - t0
    model_path = str(out / "model.zarr")
    t0 = time.perf_counter()
    fit_bases(model_path, materials, config.model_settings(), client, progress=progress and progress("bases"))
    seconds["bases"] = time.perf_counter() - t0
    render_ids: list[str] = []
    for cls in sorted({m.cls for m in materials}, key=lambda c: (c not in STRUCTURED_CLASSES, c)):
        if len(render_ids) < config.render_materials:
            render_ids.append(next(m.material_id for m in materials if m.cls == cls))
    t0 = time.perf_counter()
    result = evaluate_materials(model_path, materials, config, client, out, render_ids=render_ids,
                                progress=progress and progress("reconstruct"))
    seconds["evaluate"] = time.perf_counter() - t0
    geometry = _geometry(materials[0])
    first = next(iter(result["materials"].values()))
    times = predicted_times(config.build_device(), first["sampling"])
    t0 = time.perf_counter()
    figures: dict[str, Any] = {}
    for mid, stores in result["reconstructions"].items():
        truth_path = next(m.path for m in materials if m.material_id == mid)
        folder = out / "figures"
        figures[mid] = {"renderings": renderings(truth_path, stores, folder / mid, config.render_size, client),
                        "abrdf": abrdf_images(truth_path, stores, geometry, folder / mid)}
    seconds["render"] = time.perf_counter() - t0
    if not config.keep_reconstructions:
        shutil.rmtree(out / "reconstructions", ignore_errors=True)
        result["reconstructions"] = {}
    return {"schema": "btf-acquisition-evaluation", "config": config.to_json(),
            "scale": scale_of(materials, geometry, config), "model": model_path,
            "materials": result["materials"], "reconstructions": result["reconstructions"],
            "class_means": {m: class_means(result, m) for m in ("rel_l2_log_y", "mrmse", "mpsnr", "mre")},
            "tables": thesis_tables(result), "times": times, "claims": claims(result, times),
            "figures": figures, "strategies": strategy_names(),
            "seconds": {k: round(v, 2) for k, v in {**seconds, "total": time.perf_counter() - start}.items()}}


def write_acquisition_report(out_dir: str | os.PathLike, summary: dict[str, Any]) -> dict[str, str]:
    """``report.json`` (everything) and ``report.html`` (claims, tables, renderings, ABRDFs) in ``out_dir``."""
    from tasks.report import write_html, write_json

    out = Path(out_dir)
    write_json(out / "report.json", summary)
    sections = [{"title": "Claims of the thesis",
                 "text": "Each verdict is computed from the numbers beside it (docs/evaluation.md).",
                 "table": [["claim", "verdict", "rule", "numbers"]] + [
                     [f"({k}) {c['claim']}", c["verdict"], c["rule"], json.dumps(c["numbers"])]
                     for k, c in summary["claims"].items()]},
                {"title": "Paper 1, Table 2: log Y relative L2 reconstruction errors per class [%]",
                 "table": summary["tables"]["paper1_table2"]},
                {"title": "VMV Table 1: log Y relative errors [%], demultiplexed and de-noised",
                 "table": summary["tables"]["vmv_table1"]},
                {"title": "Every strategy, means over all held-out materials",
                 "table": summary["tables"]["all_strategies"]},
                {"title": "Predicted acquisition times [s] (btfcore.acquisition.time_model)",
                 "table": [["strategy", "evaluated device [s]", "thesis device [h]"]] + [
                     [k, round(v, 1), round(summary["times"]["thesis_device_s"][k] / 3600, 3)]
                     for k, v in summary["times"]["evaluated_device_s"].items()]}]
    for mid, fig in summary["figures"].items():
        for light, images in fig["renderings"]["images"].items():
            psnrs = fig["renderings"]["psnr_db"][light]
            sections.append({"title": f"{mid}: renderings on a sphere ({light} light), PSNR against the truth",
                             "figures": [{"file": f"figures/{mid}/{f}",
                                          "caption": name if name == "truth" else f"{name}: {psnrs[name]} dB"}
                                         for name, f in images.items()]})
        sections.append({"title": f"{mid}: centre-texel ABRDF (rows: views, columns: LEDs)",
                         "figures": [{"file": f"figures/{mid}/{f}", "caption": name}
                                     for name, f in fig["abrdf"].items()]})
    scale = summary["scale"]
    write_html(out / "report.html", "Acquisition evaluation (leave-one-out, simulated database)",
               {"scale": f"{scale['device']}: {scale['turntable_positions']} turntable x {scale['cameras']} cameras x "
                         f"{scale['leds']} LEDs = {scale['light_view_pairs']} light/view pairs, "
                         f"{scale['texture'][0]}x{scale['texture'][1]} texels, {scale['materials']} materials",
                **{f"claim ({k})": c["verdict"] for k, c in summary["claims"].items()},
                "seconds": summary["seconds"]}, sections)
    return {"report_json": str(out / "report.json"), "report_html": str(out / "report.html")}
