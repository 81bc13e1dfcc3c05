"""The Dask graphs of the acquisition evaluation: per-material bases, then every strategy on every band.

Per held-out material one chain of Dask tasks over bands of texture rows:
band maxima -> exposure gains -> band moments of the demultiplexed
measurement -> operators (leave-one-out bases, samplings, designed
patterns; once) -> band maxima of the designed patterns' images -> their
gains -> band reconstructions and error sums -> scores. All materials' chains are
submitted at once (one graph). The numerics are
:mod:`btfcore.acquisition.band_evaluation` and
:mod:`btfcore.acquisition.strategies`; this module reads and writes the
stores and wires the tasks.
"""

from __future__ import annotations

import hashlib
import os
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from btfcore.acquisition.band_evaluation import (
    BandScores,
    BandTruth,
    Moments,
    demultiplexed_moments,
    finish_scores,
    floor_name,
    image_maxima,
    measure_band,
    moments_variance,
    noise_free_band,
    pattern_maxima,
    reconstruct_strategies,
    score_band,
    with_pattern_gains,
)
from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.noise import SensorNoise, exposure_gain
from btfcore.acquisition.nonideal_measurement import (
    DomeDraws,
    draw_effects,
    measure_band_nonideal,
    multiplexed_gains,
    nonideal_gains,
    nonideal_moments,
    nonideal_patterns,
    noises_at_gains,
    registration_halo,
)
from btfcore.acquisition.reconstruct import abtf_halo
from btfcore.acquisition.strategies import Geometry, Strategy, StrategyBases, build_strategies, strategy_names
from btfcore.simulate.camera import sample_corners_px
from btfcore.simulate.nonideal import DomeNonIdeality
from tasks.buffers import heap_arrays
from tasks.compute import Progress, run_all, wait_all
from tasks.evaluate_acquisition.config import EvaluationConfig
from tasks.evaluate_acquisition.reuse import finished_store, read_record, write_record
from tasks.faults import kill_point
from tasks.model import CHANNELS, LINEAR_SVD, Material, ModelSettings, fit_material, merge_bases, open_model_store
from tasks.stores.btf import create_btf_store, open_btf_store

#: Bases the evaluation reconstructs with.
EVAL_BASES = ("log_y", "u_y", "v_y", "abtf_log_y", "als", LINEAR_SVD)


# --------------------------------------------------------------------------- bases


def fit_bases(model_path: str, materials: Sequence[Material], settings: ModelSettings, client: Any, *,
              progress: Progress | None = None) -> list[dict[str, Any]]:
    """Per-material bases of every material (:func:`tasks.model.fit_material`), one Dask task each;
    a rerun reuses every stored basis whose key is unchanged. The store is marked ``complete`` once every
    basis is in (it holds per-material bases only: the leave-one-out merges are not stored)."""
    group = open_model_store(model_path, materials)
    fits = run_all(client, fit_material, [(model_path, m, settings, EVAL_BASES) for m in materials], progress)
    group.attrs["complete"] = True
    return fits


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


# --------------------------------------------------------------------------- band tasks


def _read_rows(path: str, r0: int, r1: int) -> np.ndarray:
    return np.asarray(zarr.open_group(path, mode="r", zarr_format=3)["btf"][:, r0:r1], dtype=np.float32)


def bands(height: int, band_rows: int) -> list[tuple[int, int]]:
    """Bands of texture rows, the unit of parallel work (and of the reconstruction stores' chunks)."""
    return [(r, min(r + band_rows, height)) for r in range(0, height, band_rows)]


def band_maxima(path: str, r0: int, r1: int, patterns: np.ndarray, geometry: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Brightest noise-free value of every single-light and multiplexed image within texture rows r0:r1."""
    return image_maxima(_read_rows(path, r0, r1), patterns)


@heap_arrays()
def band_variance(path: str, r0: int, r1: int, gains: tuple[np.ndarray, np.ndarray], patterns: np.ndarray,
                  geometry: Geometry, noise: SensorNoise, seed: Sequence[int],
                  dome: tuple[DomeDraws, tuple[SensorNoise, SensorNoise]] | None = None) -> Moments:
    """(count, mean, M2) per row of the linear demultiplexed RGB (texels and channels) within rows r0:r1.

    ``dome``: the draws and the noise models at their gains of a non-ideal dome
    (:mod:`btfcore.acquisition.nonideal_measurement`); None: the ideal dome.
    """
    if dome is None:
        return demultiplexed_moments(_read_rows(path, r0, r1), r0, gains, patterns, geometry, noise, seed)
    ext = registration_halo(r0, r1, geometry.height)
    return nonideal_moments(_read_rows(path, ext.start, ext.stop), ext.start, r0, r1, gains, dome[1], patterns,
                            geometry, dome[0], seed)


@heap_arrays()
def evaluate_band(path: str, r0: int, r1: int, strategies: list[Strategy], gains: tuple[np.ndarray, np.ndarray],
                  patterns: np.ndarray, geometry: Geometry, noise: SensorNoise, seed: Sequence[int],
                  write: dict[str, str] | None = None, floors: bool = True,
                  dome: tuple[DomeDraws, tuple[SensorNoise, SensorNoise]] | None = None) -> dict[str, BandScores]:
    """Measure, reconstruct and score every strategy on texture rows r0:r1 (one Dask task).

    With ``floors`` the scores also hold each strategy's noise-free floor under
    :func:`~btfcore.acquisition.band_evaluation.floor_name` (the same strategy on
    noise-free measurements, :func:`~btfcore.acquisition.band_evaluation.reconstruct_strategies`).
    With ``write`` (``{strategy: store path}``) the reconstructions are also
    written to those stores (this band owns whole chunks of them). With ``dome`` (the draws and the
    noise models at their gains of a non-ideal dome) the measurements are the non-ideal dome's
    (:func:`~btfcore.acquisition.nonideal_measurement.measure_band_nonideal`), also those of the
    strategies with their own patterns (:func:`~btfcore.acquisition.nonideal_measurement.nonideal_patterns`,
    each strategy's shots drawn by its name); the floors stay the ideal dome's noise-free measurements.
    """
    h = geometry.height
    halo = abtf_halo(r0, r1, h, 3) if h >= 3 else slice(r0, r1)
    measure_own = None
    if dome is None:
        truth_halo = _read_rows(path, halo.start, halo.stop)
        measured = measure_band(truth_halo, halo.start, r0, r1, gains, patterns, geometry, noise, seed)
    else:
        ext = slice(max(0, halo.start - 1), min(h, halo.stop + 1))                 # the registration halo
        truth_ext = _read_rows(path, ext.start, ext.stop)
        truth_halo = truth_ext[:, halo.start - ext.start:halo.stop - ext.start]
        measured = measure_band_nonideal(truth_ext, ext.start, halo.start, halo.stop, r0, r1, gains, dome[1],
                                         patterns, geometry, dome[0], seed)

        def measure_own(strategy: Strategy) -> np.ndarray:        # a strategy's own patterns under the dome
            own = dome[0].for_patterns(strategy.patterns.shape[0], zlib.crc32(strategy.name.encode()))
            return nonideal_patterns(truth_ext, ext.start, r0, r1, strategy.gains, strategy.patterns, dome[1][1],
                                     geometry, own, seed)
    noise_free = noise_free_band(truth_halo, halo.start, r0, r1, patterns, geometry) if floors else None
    scores, ref = {}, BandTruth.of(measured[0])
    for strategy, recon, floor in reconstruct_strategies(strategies, r0, r1, truth_halo, halo.start, geometry,
                                                         measured, noise_free, noise, seed, measure_own):
        for what, x in (("", recon), (" (noise-free floor)", floor)):
            if x is not None and not np.all(np.isfinite(x)):
                bad = np.unravel_index(int(np.argmin(np.isfinite(x))), x.shape)
                raise ValueError(f"{path}: strategy {strategy.name}{what} produced a non-finite value at "
                                 f"(row {bad[0]}, texel {r0 + bad[1]}, {bad[2]}); check its operator's condition")
        scores[strategy.name] = score_band(ref, recon)
        if floor is not None:
            scores[floor_name(strategy.name)] = score_band(ref, floor)
        if write and strategy.name in write:
            group = zarr.open_group(write[strategy.name], mode="r+", zarr_format=3)
            group["btf"][:, r0:r1] = recon
            kill_point("chunk-written")
            group["written"][r0 // group["btf"].chunks[1]] = 1          # after the data it marks
    return scores


# --------------------------------------------------------------------------- reductions and operators (tasks)


def material_index(material_id: str) -> int:
    """A stable integer of a material id (the first 32 bits of its SHA-256), for per-material seeds."""
    return int(hashlib.sha256(material_id.encode()).hexdigest()[:8], 16)


def _reduce_max(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    return np.max([p[0] for p in parts], axis=0), np.max([p[1] for p in parts], axis=0)


def _gains(maxima: tuple[np.ndarray, np.ndarray], noise: SensorNoise, path: str,
           dome: tuple[DomeNonIdeality, tuple[SensorNoise, SensorNoise], int] | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
    try:
        if dome is not None:
            return nonideal_gains(maxima, dome[1], dome[0], dome[2])
        return exposure_gain(maxima[0], noise), exposure_gain(maxima[1], noise)
    except ValueError as exc:
        raise ValueError(f"{path}: btf: {exc}") from None


def _dome_draws(dome: DomeNonIdeality, geometry: Geometry, n_patterns: int, scale: np.ndarray, seed: Sequence[int],
                noises: tuple[SensorNoise, SensorNoise]) -> tuple[DomeDraws, tuple[SensorNoise, SensorNoise]]:
    """The non-ideal dome's draws for one material with its noise models (a task: computed once, read by every band)."""
    return draw_effects(dome, geometry, n_patterns, scale, seed), noises


def texels_per_px(config: EvaluationConfig) -> np.ndarray:
    """Texels per camera pixel of every view ``(n_views,)``: the texture's width over the mean side of
    the projected sample square in the view's camera pixels (the rectification's scale; the
    non-ideal dome's registration offsets and hot pixels are converted with it)."""
    device = config.build_device()
    sides = []
    for t in range(device.n_turn):
        for c in range(device.n_cam):
            corners = sample_corners_px(device.homography(t, c), device.sample_size_m)
            sides.append(np.mean(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1)))
    return device.texture_shape[1] / np.asarray(sides)


def _operators(model_path: str, materials: list[Material], material_id: str, settings: ModelSettings,
               geometry: Geometry, config: EvaluationConfig, variance: np.ndarray, patterns: np.ndarray
               ) -> tuple[list[Strategy], dict[str, Any]]:
    material = next(m for m in materials if m.material_id == material_id)
    b = leave_one_out_bases(model_path, materials, material_id, settings)
    bases = StrategyBases({c: b[c] for c in CHANNELS}, b["abtf_log_y"], b["als"], b[LINEAR_SVD])
    group = zarr.open_group(material.path, mode="r", zarr_format=3)
    sensor = config.build_device().sensor
    return build_strategies(bases, geometry, np.asarray(group["light_dir"][...]), np.asarray(group["view_dir"][...]),
                            variance, patterns, config.seed + material_index(material_id) % 100000,
                            abrdf_k_fraction=config.abrdf_k_fraction, sampling_steps=config.sampling_steps,
                            noise=SensorNoise(float(sensor.full_well_e), float(sensor.read_noise_e), config.fill),
                            single_exposure=config.non_ideal.multiplex_single_exposure)


def band_pattern_maxima(path: str, r0: int, r1: int, ops: tuple[list[Strategy], dict[str, Any]]
                        ) -> dict[str, np.ndarray]:
    """Brightest noise-free value of every image of the strategies with their own patterns within rows r0:r1."""
    return pattern_maxima(_read_rows(path, r0, r1), ops[0])


def _with_pattern_gains(ops: tuple[list[Strategy], dict[str, Any]], maxima: list[dict[str, np.ndarray]],
                        noise: SensorNoise, path: str,
                        dome: tuple[DomeNonIdeality, tuple[SensorNoise, SensorNoise], int] | None = None
                        ) -> tuple[list[Strategy], dict[str, Any]]:
    """The operators with the gains of their own patterns' images: each image's auto exposure, or under a
    non-ideal ``dome`` as its S-matrix images are exposed (:func:`multiplexed_gains`)."""
    gains_of = None if dome is None else (lambda mx: multiplexed_gains(mx, dome[1][1], dome[0], dome[2]))
    try:
        return with_pattern_gains(ops[0], maxima, noise, gains_of), ops[1]
    except ValueError as exc:
        raise ValueError(f"{path}: btf: {exc}") from None


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


def material_geometry(material: Material) -> Geometry:
    attrs = dict(zarr.open_group(material.path, mode="r", zarr_format=3).attrs)
    tcl = attrs.get("turntable_cameras_leds")
    if not tcl or int(np.prod(tcl)) != material.n_lv:
        raise ValueError(f"{material.path}: attribute turntable_cameras_leds is {tcl!r}, which does not give its "
                         f"{material.n_lv} light/view pairs; the evaluation needs the (turntable, camera, light) "
                         "layout to simulate multiplexed shots (write the store with ensure_truth_database)")
    return Geometry(int(tcl[0]), int(tcl[1]), int(tcl[2]), *material.texture_shape)


# --------------------------------------------------------------------------- reconstruction stores


def create_reconstruction_store(path: Path, truth_path: str, band_rows: int, strategy: str, key: str = "") -> str:
    """An empty ``btf-texture`` store for one strategy's reconstruction (chunks = bands), rows as the truth's.

    ``key`` is the content key of the evaluation that writes it (:func:`.reuse.scores_key`): a rerun
    reuses the store when it is complete under the same key.
    """
    truth = open_btf_store(truth_path, require_complete=False)
    n_lv, h, w, _ = truth.btf.shape
    create_btf_store(path, {"units": truth.attrs["units"], "lv_order": truth.attrs["lv_order"],
                            "reconstruction_of": truth_path, "strategy": strategy,
                            "ingest_hash": f"reconstruction-{strategy}", "key": key},
                     light_dir=truth.light_dir, view_dir=truth.view_dir, lv_index=truth.group["lv_index"][...],
                     texture_shape=(h, w), rows_per_chunk=n_lv, band=band_rows,
                     written_shape=(len(bands(h, band_rows)),))
    return str(path)


# --------------------------------------------------------------------------- the graph


def _submit_material(client: Any, model_path: str, materials: list[Material], m: Material, geometry: Geometry,
                     config: EvaluationConfig, noise: SensorNoise, write: dict[str, str] | None) -> tuple[Any, Any, Any]:
    """Submit one held-out material's chain of tasks; futures of its (scores, (info, sampling), maxima)."""
    patterns = multiplexing_patterns(geometry.n_leds)
    seed = (config.seed, material_index(m.material_id) % (1 << 31))
    parts = bands(geometry.height, config.band_rows)

    def each_band(fn: Any, *args: Any) -> list[Any]:
        return [client.submit(fn, m.path, r0, r1, *args, pure=False) for r0, r1 in parts]

    maxima = client.submit(_reduce_max, each_band(band_maxima, patterns, geometry), pure=False)
    dome, gain_dome = None, None
    if not config.non_ideal.is_ideal:                    # the effects' draws: whole arrays, once per material
        noises = noises_at_gains(noise, config.non_ideal)
        dome = client.submit(_dome_draws, config.non_ideal, geometry, patterns.shape[0], texels_per_px(config), seed,
                             noises, pure=False)
        gain_dome = (config.non_ideal, noises, geometry.n_views)
    gains = client.submit(_gains, maxima, noise, m.path, gain_dome, pure=False)
    variance = client.submit(moments_variance, each_band(band_variance, gains, patterns, geometry, noise, seed,
                                                         *([dome] if dome else [])), pure=False)
    ops = client.submit(_operators, model_path, materials, m.material_id, config.model_settings(), geometry, config,
                        variance, patterns, pure=False)
    ops = client.submit(_with_pattern_gains, ops, each_band(band_pattern_maxima, ops), noise, m.path, gain_dome,
                        pure=False)
    strategies = client.submit(_first, ops, pure=False)
    info = client.submit(_strategy_info, ops, pure=False)
    scores = client.submit(_reduce_scores, each_band(evaluate_band, strategies, gains, patterns, geometry, noise,
                                                     seed, write, True, *([dome] if dome else [])), pure=False)
    return scores, info, maxima


def _finish_material(record_path: str, key: str, cls: str, scores: dict[str, BandScores],
                     info: tuple[dict[str, Any], dict[str, Any]], maxima: tuple[np.ndarray, np.ndarray],
                     stores: dict[str, str] | None) -> dict[str, Any]:
    """One held-out material's record (scores, noise-free floors, strategies, sampling), stored under ``key``
    (a task).

    Marks its reconstruction stores complete, then writes the record atomically: a killed run
    leaves the material either finished or to be redone.
    """
    record = {"class": cls, "scores": {name: finish_scores(scores[name], maxima[0]) for name in strategy_names()},
              "floors": {name: finish_scores(scores[floor_name(name)], maxima[0]) for name in strategy_names()
                         if floor_name(name) in scores},
              "strategies": info[0], "sampling": info[1]}
    for path in (stores or {}).values():
        zarr.open_group(path, mode="r+", zarr_format=3).attrs.update({"complete": True})
    kill_point("chunk-written")                                  # scored, its record not yet written
    return write_record(record_path, key, record)


def evaluate_materials(model_path: str, materials: list[Material], config: EvaluationConfig, client: Any,
                       out_dir: str | os.PathLike, *, key: str, render_ids: Sequence[str] = (),
                       progress: Progress | None = None) -> dict[str, Any]:
    """Every strategy on every held-out material: one Dask graph of (material, band) tasks.

    Per material: band maxima -> exposure gains -> band variances of the
    demultiplexed measurement -> operators (leave-one-out bases, samplings) -> band maxima and gains of the
    designed patterns' images -> band reconstructions and error sums -> scores, stored in
    ``out_dir/scores/<material>.json`` under ``key`` (:func:`.reuse.scores_key`).
    Materials in ``render_ids`` also get their reconstructions written to
    ``out_dir/reconstructions/<material>/<strategy>.zarr``. A material whose
    record is stored under ``key`` (and, in ``render_ids``, whose
    reconstruction stores are complete under ``key``) is reused, not recomputed.

    Returns
    -------
    result : dict
        ``{"materials": {id: {"class", "scores": {strategy: metrics}, "floors": {strategy: metrics of its
        noise-free floor} (the strategies whose floor is computed), "strategies": {strategy: info},
        "sampling": ...}}, "reconstructions": {id: {strategy: path}}, "reused": {id: bool},
        "written": [ids whose reconstructions were written]}``.
    """
    device_noise = config.build_device().sensor
    noise = SensorNoise(float(device_noise.full_well_e), float(device_noise.read_noise_e), config.fill)
    out_dir = Path(out_dir)
    records, finals, stores = {}, {}, {}
    for m in materials:
        record_path = out_dir / "scores" / f"{m.material_id}.json"
        record = read_record(record_path, key)
        write = None
        if m.material_id in render_ids:
            folder = out_dir / "reconstructions" / m.material_id
            paths = {name: str(folder / f"{name}.zarr") for name in strategy_names()}
            if record is None or not all(finished_store(p, key) for p in paths.values()):
                record = None
                folder.mkdir(parents=True, exist_ok=True)
                write = {name: create_reconstruction_store(Path(p), m.path, config.band_rows, name, key)
                         for name, p in paths.items()}
            stores[m.material_id] = paths
        if record is not None:
            records[m.material_id] = record
            continue
        scores, info, maxima = _submit_material(client, model_path, materials, m, material_geometry(m), config, noise, write)
        finals[m.material_id] = client.submit(_finish_material, str(record_path), key, m.cls, scores, info, maxima,
                                              write, pure=False)
    done = dict(zip(finals, wait_all(list(finals.values()), progress)))
    return {"materials": {m.material_id: records.get(m.material_id) or done[m.material_id] for m in materials},
            "reconstructions": stores, "reused": {m.material_id: m.material_id in records for m in materials},
            "written": [mid for mid in stores if mid not in records]}
