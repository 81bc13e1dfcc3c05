"""The whole acquisition evaluation: truth database, bases, every strategy on every material, renderings."""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from btfcore.acquisition.strategies import strategy_names
from tasks.compute import Progress
from tasks.evaluate_acquisition.claims import class_means, claims, predicted_times, thesis_tables
from tasks.evaluate_acquisition.config import STRUCTURED_CLASSES, EvaluationConfig
from tasks.evaluate_acquisition.graph import _geometry, evaluate_materials, fit_bases
from tasks.evaluate_acquisition.report import abrdf_images, renderings, scale_of
from tasks.evaluate_acquisition.truth import ensure_truth_database
from tasks.model import discover


def evaluate_acquisition(db: str | os.PathLike, out_dir: str | os.PathLike, client: Any,
                         config: EvaluationConfig = EvaluationConfig(), *,
                         progress: Callable[[str], Progress | None] | None = None) -> dict[str, Any]:
    """Truth database, leave-one-out bases, every strategy on every material, renderings: the summary.

    ``progress(stage)`` may return a ``(done, total)`` callback per stage.
    The report is written by :func:`tasks.evaluate_acquisition.report.write_acquisition_report`.
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
