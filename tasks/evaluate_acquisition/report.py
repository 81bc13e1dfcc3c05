"""Renderings, ABRDF images and the report (``report.json``, ``report.html``) of the acquisition evaluation."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from btfcore.acquisition.band_evaluation import DIVERGED_MRE_PERCENT, DIVERGED_REL_L2_LOG_Y, ILL_CONDITIONED
from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.strategies import THESIS_N_S, THESIS_PAIRS, Geometry, scaled_pairs
from tasks.adaptive import adaptive_sections
from tasks.compute import wait_all
from tasks.evaluate_acquisition.claims import result_flags, thesis_tables
from tasks.evaluate_acquisition.config import EvaluationConfig
from tasks.html_report import MIN_IMAGE_PX, Cell, Row, Table, format_number, write_html
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
            "note": f"thesis: 26,136 pairs (12 turntable positions); n_s scaled by {n_pairs}/{THESIS_PAIRS}",
            "dome": "ideal" if config.non_ideal.is_ideal else config.non_ideal.to_json()}


#: How to read a strategy's error beside its noise-free floor (the every-strategy table).
FLOOR_TEXT = ("Each error stands beside its noise-free floor: the same strategy (sampling, basis, solver, "
              "regularisation and, for the thresholded de-noising, the textures it drops) run on noise-free "
              "measurements of the same truth (single-light rows of the truth; the truth's multiplexed images "
              "through the same patterns, then the same demultiplexing and de-noising). The floor is what the "
              "sampling, basis and solver give with perfect measurements; the difference between the two "
              "columns is what the sensor noise and the dome's exposure add. Plain demultiplexing of "
              "noise-free images is exact (floor 0); the projections read the truth, so their error is their "
              "floor. Floor means leave diverged floors out, as the other means do.")


#: The demo's other reports, relative to the acquisition folder: (href, label).
RELATED_REPORTS = (("../report.html", "demo report (btf demo)"), ("../model/report.html", "model database (build-db)"))


def related_reports(out: Path) -> list[tuple[str, str]]:
    """Back-links to the demo's other reports that exist; the demo's own report also while a demo writes it
    (its report comes after this one, and its ``database`` folder marks the demo's output)."""
    demo = (out.parent / "database").is_dir() and (out.parent / "model").is_dir()
    return [(href, label) for href, label in RELATED_REPORTS
            if (out / href).is_file() or (href == "../report.html" and demo)]


def scale_text(scale: dict[str, Any]) -> str:
    """What the evaluation ran on, as one sentence (:func:`scale_of`)."""
    classes = ", ".join(f"{c} ({n})" for c, n in scale["materials_per_class"].items())
    n_s = ", ".join(f"{n} -> {m}" for n, m in scale["thesis_n_s_scaled"].items())
    return (f"{scale['device']}: {scale['turntable_positions']} turntable position(s) x {scale['cameras']} cameras "
            f"x {scale['leds']:,} LEDs = {scale['light_view_pairs']:,} light/view pairs, "
            f"{scale['texture'][0]} x {scale['texture'][1]} texels; {scale['materials']} materials: {classes}; "
            f"{scale['light_turntable_pairs']:,} (light, turntable) pairs, S-matrix order {scale['s_matrix_order']}; "
            f"the thesis' sample counts n_s scaled {n_s} (sparse + multiplexed: "
            f"{scale['sparse_multiplexed_n_s']}); {scale['note']}{_dome_text(scale.get('dome', 'ideal'))}.")


def _dome_text(dome: str | dict[str, Any]) -> str:
    """The dome the measurements were simulated under (docs/simulator-physics.md, "A dome that is not ideal")."""
    if dome == "ideal":
        return "; the ideal dome"
    return "; a dome that is not ideal: " + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in dome.items()
                                                     if v not in (0, 0.0, False))


def _figure_flag(mid: str, name: str, psnr: float | None, flags: dict[str, Any]) -> str | None:
    """Why a rendering or ABRDF image of ``name`` on ``mid`` is flagged: its result diverged or is
    ill-conditioned, or its rendering is worse than black (PSNR below 0 dB)."""
    reason = flags["diverged"].get(mid, {}).get(name) or flags["ill_conditioned"].get(mid, {}).get(name)
    if psnr is not None and not psnr >= 0:
        worse = f"rendering PSNR {psnr:.4g} dB < 0 dB: its error exceeds the truth's brightest value"
        reason = f"{reason}; {worse}" if reason else worse
    return reason


def _excluded_text(claim: dict[str, Any]) -> str:
    """The diverged results a claim's means leave out, as a sentence ('' when none)."""
    excluded = claim.get("excluded") or {}
    if not excluded:
        return ""
    groups = "; ".join(f"{group}: " + ", ".join(f"{name} {n}" for name, n in row.items())
                       for group, row in excluded.items())
    return (f"Diverged results left out of its means ({groups}); a mean whose results all diverged is over "
            "them, flagged in its table.")


def _hours(seconds: float | None) -> float | None:
    """Seconds in hours (3 decimals); None where the thesis' device has no such plan (designed patterns of
    another LED count)."""
    return None if seconds is None else round(seconds / 3600, 3)


def _claim_sections(claims: dict[str, Any]) -> list[dict[str, Any]]:
    overview = [["claim", "the thesis claims", "measured here", "rule", "verdict"]] + [
        [f"({k})", c["claim"], Cell(c.get("measured", ""), flag=_excluded_text(c) or None), c["rule"], c["verdict"]]
        for k, c in claims.items()]
    sections = [{"title": "Claims of the thesis",
                 "text": ["Each verdict is computed by its rule from the numbers measured here, never written by "
                          "hand (docs/evaluation.md, \"Claims and measured numbers\"). Errors are relative L2 "
                          "errors of log Y in per cent (paper 1 §4.1.1).",
                          "Means leave diverged results out (docs/evaluation.md, \"Diverged and ill-conditioned "
                          "results\"); a mean that does is flagged in red with how many it left out."],
                 "table": overview}]
    for k, c in claims.items():
        sections.append({"title": f"Claim ({k}): {c['verdict']}",
                         "text": [f"The thesis claims: {c['claim']}.", f"Measured: {c.get('measured', '')}.",
                                  f"Rule: {c['rule']}; verdict: {c['verdict']}.", _excluded_text(c)],
                         "tables": [Table(t["rows"], t.get("caption", "")) for t in c.get("tables", [])]})
    return sections


def _flagged_rows(rows: list[list[Any]]) -> list[Any]:
    """The flagged-results table for HTML: each row flagged by its kind (the reason, its last column, says why)."""
    header, *body = rows
    return [header] + [Row(r, flag=r[-1].split(":")[0] + " (definition above; the reason in the last column)")
                       for r in body]


def _figure_sections(summary: dict[str, Any], flags: dict[str, Any]) -> list[dict[str, Any]]:
    size = summary["config"].get("render_size")
    sections = []
    for mid, fig in summary["figures"].items():
        for light, images in fig["renderings"]["images"].items():
            psnrs = fig["renderings"]["psnr_db"][light]
            sections.append({
                "title": f"{mid}: renderings on a sphere ({light} light), PSNR against the truth's rendering",
                "text": f"Rendered at {size} x {size} px and shown enlarged by whole pixels (pixelated) to at "
                        f"least {MIN_IMAGE_PX} px; click an image for the file itself. Captions in red: the "
                        "reconstruction diverged or is ill-conditioned, with the reason.",
                "figures": [{"file": f"figures/{mid}/{f}",
                             "caption": name if name == "truth" else f"{name}: {format_number(psnrs[name])} dB",
                             "flag": None if name == "truth" else _figure_flag(mid, name, psnrs[name], flags)}
                            for name, f in images.items()]})
        sections.append({"title": f"{mid}: centre-texel ABRDF (rows: views, columns: LEDs)",
                         "text": "Tone-mapped with the truth's white point; click an image for the file itself.",
                         "figures": [{"file": f"figures/{mid}/{f}", "caption": name,
                                      "flag": None if name == "truth" else _figure_flag(mid, name, None, flags)}
                                     for name, f in fig["abrdf"].items()]})
    return sections


def write_acquisition_report(out_dir: str | os.PathLike, summary: dict[str, Any]) -> dict[str, str]:
    """``report.json`` (everything) and ``report.html`` (claims, tables, flags, renderings, ABRDFs) in ``out_dir``.

    ``summary`` is :func:`tasks.evaluate_acquisition.run.evaluate_acquisition`'s; the HTML's tables are
    :func:`.claims.thesis_tables` with their flags (diverged and ill-conditioned results in red, with the
    reason; means that leave diverged results out), the claims' own tables, and the figures.
    """
    from tasks.report import reused_text, write_json

    out = Path(out_dir)
    write_json(out / "report.json", summary)
    result = {"materials": summary["materials"]}
    flags = summary.get("flags") or result_flags(result)
    tables = thesis_tables(result, flagged=True)
    n_results = sum(len(rec["scores"]) for rec in summary["materials"].values())
    n_diverged = sum(len(v) for v in flags["diverged"].values())
    n_ill = sum(len(v) for v in flags["ill_conditioned"].values())
    sections = _claim_sections(summary["claims"])
    sections.append({
        "title": "Diverged and ill-conditioned results",
        "text": [f"{n_diverged} of {n_results} (material, strategy) results diverged and {n_ill} are "
                 "ill-conditioned. Diverged: a score that is not finite, mRE above "
                 f"{format_number(DIVERGED_MRE_PERCENT)} % or a log Y relative L2 error above "
                 f"{format_number(100 * DIVERGED_REL_L2_LOG_Y)} %; every mean in this report leaves them out. "
                 "Ill-conditioned: a condition number of the (sampled) basis rows above "
                 f"{ILL_CONDITIONED:.0e}, or fewer samples than basis vectors; shown, kept in the means.",
                 "The condition number is that of the strategy's solve operator (of its log Y operator for the "
                 "paper 1 strategies)."],
        "table": _flagged_rows(tables["flagged_results"]) if len(tables["flagged_results"]) > 1 else None})
    sections += [{"title": "Paper 1, Table 2: log Y relative L2 reconstruction errors per class [%]",
                  "table": tables["paper1_table2"]},
                 {"title": "VMV Table 1: log Y relative errors [%], demultiplexed and de-noised",
                  "table": tables["vmv_table1"]},
                 {"title": "Every strategy, means over all held-out materials, beside its noise-free floor",
                  "text": [FLOOR_TEXT, "mRMSE, mPSNR and mRE: SR paper eqs. (8)-(10) on linear RGB; mRMSE in the "
                                       "truth's linear units."],
                  "table": tables["all_strategies"]},
                 {"title": "Predicted acquisition times (btfcore.acquisition.time_model)",
                  "table": [["strategy", "evaluated device [s]", "thesis device [h]"]] + [
                      [k, round(v, 1), _hours(summary["times"]["thesis_device_s"].get(k))]
                      for k, v in summary["times"]["evaluated_device_s"].items()]}]
    sections += adaptive_sections(summary.get("adaptive"))
    sections += _figure_sections(summary, flags)
    head = {"scale": scale_text(summary["scale"]),
            **{f"claim ({k})": c["verdict"] for k, c in summary["claims"].items()},
            "diverged results (left out of the means)": Cell(f"{n_diverged} of {n_results}",
                                                             flag="see 'Diverged and ill-conditioned results'"
                                                             if n_diverged else None),
            "time [s]": summary["seconds"],
            "reused from an earlier run": reused_text(summary["reused"])}
    write_html(out / "report.html", "Acquisition evaluation (leave-one-out, simulated database)", head, sections,
               related_reports(out))
    return {"report_json": str(out / "report.json"), "report_html": str(out / "report.html")}
