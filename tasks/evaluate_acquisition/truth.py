"""The truth database of the acquisition evaluation: one noise-free ``btf-texture`` store per material.

Each store is rendered straight from the virtual dome's renderer
(:func:`btfcore.simulate.render.render_view` at twice the texture resolution,
box-filtered, as ``tasks.simulate`` makes its truth), one Dask task per view.
:func:`tasks.model.discover` accepts the stores, so the model database fits
its bases on them.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from btfcore.dome import Device
from tasks.buffers import heap_arrays
from tasks.compute import Progress, wait_all
from tasks.evaluate_acquisition.config import TRUTH_KIND, EvaluationConfig, TruthSpec, truth_specs
from tasks.faults import kill_point
from tasks.staging import store_attrs
from tasks.stores.btf import LV_ORDER, BtfStore, create_btf_store


def _truth_hash(config: EvaluationConfig, spec: TruthSpec) -> str:
    return hashlib.sha256(f"{config.truth_key()}/{spec.material_id}/{spec.seed}".encode()).hexdigest()[:16]


def create_truth_store(path: Path, config: EvaluationConfig, spec: TruthSpec, device: Device) -> BtfStore:
    """An empty truth store (``btf-texture`` 1.0, rows ``(turntable, camera, light)``), one chunk per view."""
    light, view, lv_index = device.lv_directions()
    return create_btf_store(path, {
        "kind": TRUTH_KIND,
        "units": "radiance per unit irradiance (BTF value incl. cos theta_i), noise-free ground truth",
        "lv_order": LV_ORDER, "turntable_cameras_leds": [device.n_turn, device.n_cam, device.n_leds],
        "ingest_hash": _truth_hash(config, spec), "evaluation": config.to_json(),
        "material": {"material_id": spec.material_id, "class": spec.class_name, "seed": spec.seed},
    }, light_dir=light, view_dir=view, lv_index=lv_index, texture_shape=device.texture_shape,
        rows_per_chunk=device.n_leds, band=device.texture_shape[0], written_shape=(device.n_turn, device.n_cam))


def prepare_truth_material(spec: TruthSpec, config: EvaluationConfig) -> tuple[Any, np.ndarray]:
    """The material's maps at twice the texture resolution and its horizon map."""
    from btfcore.simulate.materials import make_material
    from btfcore.simulate.render import horizon_map
    from tasks.textures import load_texture_sources

    h, w = config.build_device().texture_shape
    maps = make_material(spec.class_name, spec.seed, (2 * h, 2 * w), load_texture_sources())
    return maps, horizon_map(maps.height)


@heap_arrays()
def render_truth_view(path: str, config: EvaluationConfig, prepared: tuple[Any, np.ndarray], t: int, c: int) -> int:
    """Render the truth of one view (all lights) at 2x, box-filter it and write its chunk."""
    from btfcore.simulate.render import downsample2, render_view

    device = config.build_device()
    maps, horizon = prepared
    truth = downsample2(render_view(maps, device.view_dir(t, c), device.light_dirs(t), horizon))
    v = t * device.n_cam + c
    group = zarr.open_group(path, mode="r+", zarr_format=3)
    group["btf"][v * device.n_leds:(v + 1) * device.n_leds] = truth.astype(np.float32)
    kill_point("chunk-written")
    group["written"][t, c] = 1                                  # after the data it marks
    return v


def pending_truth_specs(config: EvaluationConfig, db: str | os.PathLike) -> list[TruthSpec]:
    """The materials of ``config`` whose truth store in ``db`` is not finished (a rerun writes only these).

    Raises
    ------
    ValueError
        When a store at one of the paths holds something else (another
        configuration's truth, or not a truth store): nothing is overwritten.
    """
    pending = []
    for spec in truth_specs(config):
        path = Path(db) / f"{spec.material_id}.zarr"
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
        pending.append(spec)
    return pending


def ensure_truth_database(config: EvaluationConfig, db: str | os.PathLike, client: Any, *,
                          progress: Progress | None = None) -> list[str]:
    """Write the truth stores of ``config`` into ``db`` (reusing finished ones), one Dask task per view.

    An unfinished store of this configuration (a killed run's) is resumed: only its views whose
    resume marker is not set are rendered.

    Raises
    ------
    ValueError
        When a store at one of the paths holds something else (:func:`pending_truth_specs`).
    """
    db = Path(db)
    db.mkdir(parents=True, exist_ok=True)
    device = config.build_device()
    futures = []
    for spec in pending_truth_specs(config, db):
        path = db / f"{spec.material_id}.zarr"
        if (store_attrs(path) or {}).get("ingest_hash") != _truth_hash(config, spec):
            create_truth_store(path, config, spec, device)
        written = zarr.open_group(str(path), mode="r", zarr_format=3)["written"][...]
        views = [(t, c) for t in range(device.n_turn) for c in range(device.n_cam) if not written[t, c]]
        if not views:
            continue
        prepared = client.submit(prepare_truth_material, spec, config, pure=False)
        futures += [client.submit(render_truth_view, str(path), config, prepared, t, c, pure=False)
                    for t, c in views]
    wait_all(futures, progress)
    paths = [str(db / f"{spec.material_id}.zarr") for spec in truth_specs(config)]
    for path in paths:
        group = zarr.open_group(path, mode="r+", zarr_format=3)
        if not group.attrs.get("complete"):
            group.attrs.update({"complete": True})
    return paths
