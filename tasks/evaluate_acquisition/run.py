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
from tasks.evaluate_acquisition.claims import (
    class_means,
    claims,
    floor_means,
    predicted_times,
    result_flags,
    thesis_tables,
)
from tasks.evaluate_acquisition.config import STRUCTURED_CLASSES, EvaluationConfig, truth_specs
from tasks.evaluate_acquisition.graph import EVAL_BASES, material_geometry, evaluate_materials, fit_bases
from tasks.evaluate_acquisition.report import abrdf_images, env_map_path, renderings, scale_of
from tasks.evaluate_acquisition.reuse import figures_key, figures_present, read_record, scores_key, write_record
from tasks.evaluate_acquisition.truth import ensure_truth_database, pending_truth_specs
from tasks.adaptive import evaluate_adaptive
from tasks.model import Material, discover


def _render_figures(render_ids: list[str], reused: dict[str, Any], stores: dict[str, dict[str, str]],
                    materials: list[Material], folder: Path, key: str, config: EvaluationConfig, client: Any,
                    progress: Progress | None = None) -> dict[str, Any]:
    """Renderings and ABRDF images of every material in ``render_ids``: those in ``reused`` as they are,
    the others rendered from their reconstruction ``stores`` and stored under ``key`` (``figures.json``);
    ``progress(done, total)`` after each material rendered."""
    geometry = material_geometry(materials[0])
    pending = [mid for mid in render_ids if mid not in reused]
    for i, mid in enumerate(pending):
        if progress:
            progress(i, len(pending))
        truth_path = next(m.path for m in materials if m.material_id == mid)
        figure = {"renderings": renderings(truth_path, stores[mid], folder / mid, config.render_size, client),
                  "abrdf": abrdf_images(truth_path, stores[mid], geometry, folder / mid)}
        reused[mid] = write_record(folder / mid / "figures.json", key, figure)
    if progress and pending:
        progress(len(pending), len(pending))
    return {mid: reused[mid] for mid in render_ids}


def evaluate_acquisition(db: str | os.PathLike, out_dir: str | os.PathLike, client: Any,
                         config: EvaluationConfig = EvaluationConfig(), *,
                         progress: Callable[[str], Progress | None] | None = None) -> dict[str, Any]:
    """Truth database, leave-one-out bases, every strategy on every material, renderings: the summary.

    ``progress(stage)`` may return a ``(done, total)`` callback per stage.
    The report is written by :func:`tasks.evaluate_acquisition.report.write_acquisition_report`.
    A rerun on the same ``out_dir`` reuses every finished result whose inputs are unchanged
    (:mod:`tasks.evaluate_acquisition.reuse`); the summary's ``"reused"`` says how much,
    ``{what: [reused, total]}``, and ``"key"`` holds the content keys. Each material's record has its
    strategies' noise-free floors beside their scores (``"floors"``), and ``"floors"`` of the summary
    the kind of each strategy's floor and their means (:func:`.claims.floor_means`).
    """
    start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    n_truth = len(truth_specs(config))
    truth_reused = n_truth - len(pending_truth_specs(config, db))
    ensure_truth_database(config, db, client, progress=progress and progress("truth BTFs"))
    materials = discover(db)
    seconds["truth"] = time.perf_counter() - t0
    model_path = str(out / "model.zarr")
    t0 = time.perf_counter()
    fits = fit_bases(model_path, materials, config.model_settings(), client, progress=progress and progress("bases"))
    seconds["bases"] = time.perf_counter() - t0
    fitted = [how for fit in fits for how in fit["bases"].values()]
    key = scores_key(config, model_path, materials, EVAL_BASES)
    fig_key = figures_key(key, config.render_size, env_map_path())
    render_ids: list[str] = []
    for cls in sorted({m.cls for m in materials}, key=lambda c: (c not in STRUCTURED_CLASSES, c)):
        if len(render_ids) < config.render_materials:
            render_ids.append(next(m.material_id for m in materials if m.cls == cls))
    figures: dict[str, Any] = {}
    for mid in render_ids:
        record = read_record(out / "figures" / mid / "figures.json", fig_key)
        if record is not None and figures_present(out / "figures" / mid, record):
            figures[mid] = record
    t0 = time.perf_counter()
    result = evaluate_materials(model_path, materials, config, client, out, key=key,
                                render_ids=[m for m in render_ids if m not in figures or config.keep_reconstructions],
                                progress=progress and progress("reconstruct"))
    seconds["evaluate"] = time.perf_counter() - t0
    rendered = [mid for mid in render_ids if mid not in figures]
    figures = _render_figures(render_ids, figures, result["reconstructions"], materials, out / "figures", fig_key,
                              config, client, progress=progress("render") if progress and rendered else None)
    seconds["render"] = time.perf_counter() - t0 - seconds["evaluate"]
    if not config.keep_reconstructions:
        shutil.rmtree(out / "reconstructions", ignore_errors=True)
        result["reconstructions"] = {}
    n_recon = len(render_ids) * len(strategy_names())
    reused = {"truth_stores": [truth_reused, n_truth], "bases": [fitted.count("reused"), len(fitted)],
              "material_scores": [sum(result["reused"].values()), len(materials)],
              "reconstructions": [n_recon - len(result["written"]) * len(strategy_names()), n_recon],
              "figures": [len(render_ids) - len(rendered), len(render_ids)]}
    geometry = material_geometry(materials[0])
    first = next(iter(result["materials"].values()))
    times = predicted_times(config.build_device(), first["sampling"])
    t0 = time.perf_counter()
    adaptive = (evaluate_adaptive(model_path, materials, config, client, out, result, key,   # docs/adaptive-capture.md
                                  progress=progress and progress("adaptive loop")) if config.adaptive else None)
    seconds["adaptive"] = time.perf_counter() - t0
    return {"schema": "btf-acquisition-evaluation", "adaptive": adaptive, "config": config.to_json(),
            "scale": scale_of(materials, geometry, config), "model": model_path,
            "materials": result["materials"], "reconstructions": result["reconstructions"],
            "class_means": {m: class_means(result, m) for m in ("rel_l2_log_y", "mrmse", "mpsnr", "mre")},
            "tables": thesis_tables(result), "times": times, "claims": claims(result, times),
            "flags": result_flags(result), "floors": floor_means(result),
            "figures": figures, "strategies": strategy_names(), "key": {"scores": key, "figures": fig_key},
            "reused": reused,
            "seconds": {k: round(v, 2) for k, v in {**seconds, "total": time.perf_counter() - start}.items()}}
