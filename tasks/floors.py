"""Error floors of ingest: the same pipeline on a noise-free capture and on an ideal full-RGB sensor.

The ingest errors of a simulated capture (:func:`tasks.ingest.btf_error_against_truth`) mix three
causes: the sensor's noise, the dome's sampling (a Bayer mosaic at about 1.5 camera pixels per
texel on the tiny dome aliases texel-scale patterns, and demosaicing a fine weave seen at a grazing
angle shows false colour) and the pipeline's own approximations (HDR merge, rectification's
resampling, white-standard calibration). The floors separate them by running the same chain on the
same material, views, exposure brackets and dark-current maps with two other sensors
(:class:`btfcore.simulate.sensor.SensorModel`):

* ``noise_free``: the camera's Bayer frames and dark frames at their noise-free mean
  (:func:`btfcore.simulate.sensor.expected_dn`, not rounded): what is left is the sampling and
  the pipeline;
* ``full_rgb``: noise-free, and every pixel measures R, G and B, so ingest merges each channel and
  does not demosaic: what is left is the pipeline (rectification's resampling of the projected
  texture) alone.

Ingest error minus the noise-free floor is the noise's share; noise-free floor minus full-RGB floor
the mosaic's (Bayer aliasing and demosaicing); the full-RGB floor the rest of the pipeline.

The capture store holds uint16 Bayer frames (``btf-capture`` 1.0), which can hold neither float
noise-free frames nor three channels per pixel, so the floors are evaluated in memory, not written
as capture stores: per view, the simulator's :func:`tasks.simulate.pattern_frames` from the stored
2x ground truth, exposed by :func:`btfcore.simulate.sensor.expose` with the other sensor, then the
ingest's own :func:`btfcore.capture.view_chain.process_view` with the arguments
:func:`tasks.ingest.view_chain_arguments` gives it, and the errors of
:func:`tasks.ingest.errors_against_truth`. One Dask task per material.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from btfcore.capture.view_chain import IngestSettings, process_view, view_window
from btfcore.simulate.sensor import SensorModel, dark_frames, expose
from tasks.buffers import heap_arrays
from tasks.compute import Progress, run_all
from tasks.ingest import errors_against_truth, view_chain_arguments
from tasks.simulate import SimulationConfig, camera_dark_map, pattern_frames
from tasks.stores import CaptureStore, open_capture_store

#: The sensors of the floors, by the name the reports use.
FLOOR_SENSORS: dict[str, SensorModel] = {"noise_free": SensorModel(noise=False),
                                         "full_rgb": SensorModel(noise=False, mosaic=False)}

#: Part of the floors' reuse key: raise it when the floors' numerics change.
FLOORS_VERSION = 1


def floor_textures(capture: CaptureStore, config: SimulationConfig, t: int, c: int, sensor: SensorModel,
                   settings: IngestSettings = IngestSettings()) -> np.ndarray:
    """View ``(t, c)`` of a simulated single-LED capture as ingest would see it from another sensor.

    Parameters
    ----------
    capture : CaptureStore
        A simulated capture with its ground truth (``truth/btf_2x``); its exposure brackets are reused.
    config : SimulationConfig
        The simulation that made it (the device, its overrides).
    sensor : SensorModel
        The sensor the frames and dark frames are exposed with (:data:`FLOOR_SENSORS`).

    Returns
    -------
    textures : (n_leds, h, w, 3) ndarray of float32
        Rectified linear textures, DN/s (uncalibrated), as :func:`tasks.ingest.ingest_view` writes them.
    """
    device = config.build_device()
    meta = capture.meta
    n_leds = capture.n_leds
    lv0 = (t * capture.n_cam + c) * n_leds
    truth_2x = np.asarray(capture.truth["btf_2x"][lv0:lv0 + n_leds], dtype=np.float32)
    frames, _ = pattern_frames(device, capture.illumination.astype(np.float32), truth_2x, t, c)
    times = np.asarray(capture.exposure_time[t, c], dtype=np.float64)           # the capture's brackets
    dark_map = camera_dark_map(device, c)
    raw = expose(frames[:, None], times, device.sensor, dark_map, None, model=sensor)
    darks = dark_frames(device.sensor, dark_map, meta.dark_exposure_time, device.roi_shape, None, sensor)
    window = view_window(capture.homography[t, c], capture.roi_shape, tuple(meta.texture_shape),
                         meta.sample_size_m, settings)
    arguments = {**view_chain_arguments(capture, t, c, window, settings),
                 "dark_frames": darks, "bayer_pattern": meta.bayer_pattern if sensor.mosaic else None}
    textures, _ = process_view(raw[:, :, window[0], window[1]], times, capture.illumination, **arguments)
    return textures


@heap_arrays()
def material_floors(capture_path: str, config: SimulationConfig,
                    settings: IngestSettings = IngestSettings()) -> dict[str, dict[str, float]]:
    """Every floor of one material: ``{sensor: errors}``, the errors of
    :func:`tasks.ingest.errors_against_truth` (``relative_l2_linear``, ``relative_l2_log_y``; fitted:
    one least-squares scale per LED and channel, as the ingest's figures without ``calibrated_``)."""
    capture = open_capture_store(capture_path)
    truth = np.asarray(capture.truth["btf"][...], dtype=np.float64)
    floors = {}
    for name, sensor in FLOOR_SENSORS.items():
        btf = np.concatenate([floor_textures(capture, config, t, c, sensor, settings)
                              for t in range(capture.n_turn) for c in range(capture.n_cam)])
        floors[name] = errors_against_truth(btf, truth, capture.n_leds)
    return floors


def floors_key(config: SimulationConfig, capture_paths: Sequence[str], settings: IngestSettings) -> str:
    """Content key of the floors of ``capture_paths``: their config hashes, the settings, the version."""
    hashes = [open_capture_store(p).group.attrs.get("provenance", {}).get("config_hash") for p in capture_paths]
    payload = {"config": config.to_json(), "captures": hashes, "settings": asdict(settings),
               "version": FLOORS_VERSION}
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def ingest_floors(config: SimulationConfig, capture_paths: Sequence[str], client: Any, record: str | os.PathLike,
                  *, settings: IngestSettings = IngestSettings(),
                  progress: Progress | None = None) -> dict[str, Any]:
    """The floors of every simulated single-LED capture, one Dask task per material, reused from
    ``record`` (a JSON file) when it holds them under the same key.

    Returns
    -------
    dict
        ``floors``: ``{material stem: {"noise_free": errors, "full_rgb": errors}}``; ``seconds``;
        ``reused``: ``{"materials": [reused, total]}``.
    """
    from tasks.evaluate_acquisition.reuse import read_record, write_record

    start = time.perf_counter()
    paths = [str(p) for p in capture_paths]
    key = floors_key(config, paths, settings)
    stored = read_record(record, key)
    if stored is not None:
        return {"floors": stored["floors"], "seconds": 0.0, "reused": {"materials": [len(paths), len(paths)]}}
    results = run_all(client, material_floors, [(p, config, settings) for p in paths], progress)
    floors = write_record(record, key, {"floors": {Path(p).stem: r for p, r in zip(paths, results)}})["floors"]
    return {"floors": floors, "seconds": round(time.perf_counter() - start, 3),
            "reused": {"materials": [0, len(paths)]}}
