"""Renderings, ABRDF images and the report (``report.json``, ``report.html``) of the acquisition evaluation."""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.strategies import THESIS_N_S, THESIS_PAIRS, Geometry, scaled_pairs
from tasks.compute import wait_all
from tasks.evaluate_acquisition.config import EvaluationConfig
from tasks.model import Material


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
        truth_png = str(out / f"render_{light}_truth.png")
        truth = client.submit(render_one, truth_path, truth_png, size, env_path, None, pure=False).result()
        covered = truth["image"][truth["mask"]]
        white = float(np.percentile(covered[covered > 0], 99.5)) if np.any(covered > 0) else None
        # the truth's PNG again with the common white point, so that all images compare
        truth = client.submit(render_one, truth_path, truth_png, size, env_path, white, pure=False).result()
        names = list(stores)
        rendered = wait_all([client.submit(render_one, stores[name], str(out / f"render_{light}_{name}.png"), size,
                                           env_path, white, pure=False) for name in names])
        result["images"][light] = {"truth": truth["png"]}
        result["psnr_db"][light] = {}
        peak = float(truth["image"][truth["mask"]].max())
        for name, r in zip(names, rendered):
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


def write_acquisition_report(out_dir: str | os.PathLike, summary: dict[str, Any]) -> dict[str, str]:
    """``report.json`` (everything) and ``report.html`` (claims, tables, renderings, ABRDFs) in ``out_dir``."""
    from tasks.report import reused_text, write_html, write_json

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
                "seconds": summary["seconds"],
                "reused from an earlier run": reused_text(summary["reused"])}, sections)
    return {"report_json": str(out / "report.json"), "report_html": str(out / "report.html")}
