"""Run reports: ``report.json`` for machines, ``report.html`` with PNGs for people.

Figures are made from what the run wrote to disk (capture stores and their
ground truth), so a report shows the data a later stage will read.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from btfcore.simulate.camera import homography_sample_mask
from btfcore.dome import Device
from btfcore.model.colour import REC709_LUMA
from btfcore.simulate.sensor import WELL_EXPOSED
from btfcore.render.tonemap import srgb_encode, tonemap
from tasks.stores import CaptureStore, open_capture_store

#: Rows of the ground truth read for statistics (a subsample keeps reports cheap
#: on bonn-dome2, whose truth is ~5 GB per material).
STAT_ROWS = 1024


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def reused_text(reused: dict[str, Sequence[int]]) -> str:
    """What a stage reused from an earlier run, for a log line or a report: ``"96 of 96 views, 12 of 12 bases"``.

    ``reused`` is a stage's ``"reused"``: ``{what: [reused, total]}`` (``_`` in ``what`` read as a space).
    """
    return ", ".join(f"{n} of {total} {what.replace('_', ' ')}" for what, (n, total) in reused.items())


def write_json(path: str | Path, data: dict[str, Any]) -> Path:
    """Write plain JSON (numpy values converted, NaN/Inf refused) atomically."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, default=_json_default, allow_nan=False))
    tmp.replace(path)
    return path


def save_png(path: Path, rgb: np.ndarray, scale: int | tuple[int, int] = 1) -> str:
    """Write an 8-bit image, enlarged by whole pixels (``scale`` or ``(sy, sx)``)."""
    sy, sx = (scale, scale) if isinstance(scale, int) else scale
    if sy > 1 or sx > 1:
        rgb = np.repeat(np.repeat(rgb, sy, axis=0), sx, axis=1)
    image = rgb[..., ::-1] if rgb.ndim == 3 else rgb
    if not cv2.imwrite(str(path), np.ascontiguousarray(image)):
        raise OSError(f"could not write {path}")
    return path.name


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ REC709_LUMA.astype(rgb.dtype)


def material_statistics(store: CaptureStore) -> dict[str, Any]:
    """Figures of one simulated store: dynamic range, exposures, saturation, exposure quality."""
    truth = store.group["truth"]["btf"]
    n_lv = truth.shape[0]
    rows = np.unique(np.linspace(0, n_lv - 1, min(n_lv, STAT_ROWS)).astype(int))
    lum = _luminance(np.asarray(truth.get_orthogonal_selection((rows,)), dtype=np.float64))
    p_lo, p_hi = np.percentile(lum, [0.1, 99.9])
    positive = lum[lum > 0]
    times = np.asarray(store.group["exposure_time"][...])
    meta = store.meta
    # Exposure quality of the real (noisy) frames of a few views: a sample pixel is
    # well exposed when one frame has it inside the sensor's WELL_EXPOSED range.
    span = float(meta.white_level - meta.black_level)
    well, saturated = [], []
    views = [(t, c) for t in range(store.n_turn) for c in range(store.n_cam)]
    for t, c in views[:: max(1, len(views) // 8)]:  # up to ~8 views spread over the capture
        frames, _ = store.read_bracket(t, c, 0)
        level = (frames.astype(np.float64) - meta.black_level) / span
        mask = homography_sample_mask(store.homography[t, c], store.roi_shape, meta.sample_size_m)
        good = ((level > WELL_EXPOSED[0]) & (level < WELL_EXPOSED[1])).any(axis=0)
        well.append(float(good[mask].mean()))
        saturated.append(float((frames[0] >= meta.white_level)[mask].mean()))
    return {
        "n_lv": int(n_lv),
        # brightest over darkest non-zero luminance of the (noise-free) truth
        "dynamic_range": float(positive.max() / positive.min()) if positive.size else 0.0,
        "dynamic_range_p99.9_over_p0.1": float(p_hi / max(p_lo, 1e-30)),
        "luminance_p0.1": float(p_lo),
        "luminance_p99.9": float(p_hi),
        "exposure_time_s": {"min": float(times.min()), "max": float(times.max())},
        "well_exposed_fraction_min": float(min(well)),
        "saturated_in_shortest_fraction_max": float(max(saturated)),
    }


def ingest_validity(btf_path: str | Path, capture_path: str | Path, *, listed: int = 10) -> dict[str, Any]:
    """How much of each raw bracket an ingest could use (the BTF store's ``valid_fraction``).

    A bracket in which no raw pixel has an exposure that is neither saturated
    nor near-black holds no radiance: its BTF rows are lower bounds (all
    saturated) or noise (all black). Such brackets are counted, the first
    ``listed`` are given as ``(t, c, i)`` with the saturated share of their
    shortest exposure, and ``problem`` says where they are and what to do
    (``None`` when every bracket has a usable pixel).
    """
    import zarr

    group = zarr.open_group(str(btf_path), mode="r", zarr_format=3)
    valid = np.asarray(group["valid_fraction"][...])
    unusable = np.argwhere(valid <= 0)
    summary: dict[str, Any] = {"min": float(valid.min()), "mean": float(valid.mean()),
                               "brackets_without_usable_pixel": int(len(unusable)), "listed": [], "problem": None}
    if not len(unusable):
        return summary
    capture = open_capture_store(capture_path)
    threshold = group.attrs["settings"]["saturation_margin"] * capture.meta.white_level
    for t, c, i in unusable[:listed].tolist():
        saturated = float(np.mean(capture.raw[t, c, i, 0] >= threshold))
        summary["listed"].append({"t_c_i": [t, c, i], "shortest_exposure_saturated": round(saturated, 4)})
    where = ", ".join(f"({t}, {c}, {i}) [shortest exposure {item['shortest_exposure_saturated']:.0%} saturated]"
                      for item in summary["listed"] for t, c, i in [item["t_c_i"]])
    more = f" (+{len(unusable) - listed} more)" if len(unusable) > listed else ""
    summary["problem"] = (
        f"{capture_path}: raw[(t, c, i)={where}{more}]: {len(unusable)} of {valid.size} bracket(s) have no pixel "
        "with an exposure that is neither saturated nor near-black, so their BTF rows are not radiance. "
        "Capture those brackets again with shorter exposures where saturated (longer exposures or a working "
        "LED where black), then import and ingest again")
    return summary


def pyplot() -> Any:
    """matplotlib's pyplot on the file-only Agg backend (no display on workers or CI)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: Path) -> str:
    """Lay out, write (90 dpi) and close a figure; its file name."""
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    pyplot().close(fig)
    return path.name


def plot_dome(device: Device, path: Path) -> str:
    """Hemisphere plot of LEDs, cameras and the turntable's view directions."""
    plt = pyplot()

    def polar(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = np.atleast_2d(v)
        return np.arctan2(v[:, 1], v[:, 0]), np.degrees(np.arccos(np.clip(v[:, 2], -1, 1)))

    fig = plt.figure(figsize=(11, 5))
    ax = fig.add_subplot(1, 2, 1, projection="polar")
    leds = device.led_position / np.linalg.norm(device.led_position, axis=1, keepdims=True)
    cams = device.camera_position / np.linalg.norm(device.camera_position, axis=1, keepdims=True)
    ax.scatter(*polar(leds), s=14, c="orange", label=f"{device.n_leds} lights", zorder=3)
    ax.scatter(*polar(cams), s=40, marker="^", c="tab:blue", label=f"{device.n_cam} cameras", zorder=4)
    views = np.array([device.view_dir(t, c) for t in range(device.n_turn) for c in range(device.n_cam)])
    if device.n_turn > 1:
        ax.scatter(*polar(views), s=8, marker="x", c="tab:gray",
                   label=f"views in sample frame ({device.n_turn} turntable positions)", zorder=2)
    ax.set_rmax(90)
    ax.set_rticks([15, 30, 45, 60, 75, 90])
    ax.set_title(f"{device.name}: top view (radius = theta, degrees)")
    ax.legend(loc="lower left", bbox_to_anchor=(-0.15, -0.22), fontsize=8)

    ax3 = fig.add_subplot(1, 2, 2, projection="3d")
    ax3.scatter(*device.led_position.T, s=6, c="orange")
    ax3.scatter(*device.camera_position.T, s=30, marker="^", c="tab:blue")
    half = device.sample_size_m / 2
    square = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0], [-half, -half, 0]])
    ax3.plot(*square.T, c="k")
    radius = float(np.linalg.norm(device.camera_position, axis=1).max())
    angle = np.linspace(0, 2 * np.pi, 100)
    ax3.plot(0.15 * radius * np.cos(angle), 0.15 * radius * np.sin(angle), 0 * angle, c="tab:green",
             label="turntable")
    ax3.set_box_aspect((1, 1, 0.5))
    ax3.set_title("dome (metres)")
    ax3.legend(fontsize=8)
    return save_figure(fig, path)


def raw_frame_images(store: CaptureStore, out: Path, prefix: str, views: Sequence[tuple[int, int, int]]) -> list[dict]:
    """Tone-mapped raw frames: each bracket member as the grey mosaic, scaled to the sensor range."""
    meta = store.meta
    span = float(meta.white_level - meta.black_level)
    items = []
    for t, c, i in views:
        frames, times = store.read_bracket(t, c, i)
        tiles = [srgb_encode((f.astype(np.float64) - meta.black_level) / span) for f in frames]
        strip = np.concatenate([np.pad(tile, 2, constant_values=1.0) for tile in tiles], axis=1)
        name = save_png(out / f"{prefix}_raw_t{t}_c{c}_i{i}.png", np.round(strip * 255).astype(np.uint8),
                         scale=max(1, 256 // frames.shape[-2]))
        items.append({"file": name, "turntable": t, "camera": c, "illumination": i,
                      "exposure_time_s": [float(x) for x in times]})
    return items


def pick_lv_pairs(store: CaptureStore) -> list[tuple[int, str]]:
    """A few telling light/view pairs: frontal, specular, grazing view, grazing light."""
    light = np.asarray(store.group["truth"]["light_dir"][...])
    view = np.asarray(store.group["truth"]["view_dir"][...])
    mirror = light * np.array([-1, -1, 1])
    picks = {
        "frontal view, high light": np.argmax(view[:, 2] * 4 + light[:, 2]),
        "specular": np.argmax(np.sum(mirror * view, axis=1) + 0.1 * view[:, 2]),
        "grazing view": np.argmin(view[:, 2] - 0.1 * light[:, 2]),
        "grazing light": np.argmin(light[:, 2] - 0.1 * view[:, 2]),
    }
    return [(int(lv), label) for label, lv in picks.items()]


def texture_images(store: CaptureStore, out: Path, prefix: str) -> list[dict]:
    """Ground-truth textures at a few light/view pairs, one white point per material."""
    truth = store.group["truth"]["btf"]
    pairs = pick_lv_pairs(store)
    textures = np.stack([truth[lv] for lv, _ in pairs])
    white = float(np.percentile(textures, 99.5))
    items = []
    for (lv, label), texture in zip(pairs, textures):
        name = save_png(out / f"{prefix}_texture_lv{lv}.png", tonemap(texture, white=white),
                         scale=max(1, 128 // texture.shape[0]))
        items.append({"file": name, "lv": lv, "label": label})
    return items


def ingest_images(store: CaptureStore, btf_path: str | Path, out: Path, prefix: str) -> list[dict]:
    """Ground truth beside the ingested BTF at the pairs of :func:`pick_lv_pairs`, one white point
    (the truth's) when the BTF is calibrated to the truth's unit, its own otherwise."""
    import zarr

    truth = store.group["truth"]["btf"]
    btf = zarr.open_group(str(btf_path), mode="r", zarr_format=3)
    calibrated = bool((btf.attrs.get("radiometric") or {}).get("white_standard"))
    pairs = pick_lv_pairs(store)
    got = np.stack([btf["btf"][lv] for lv, _ in pairs])
    want = np.stack([truth[lv] for lv, _ in pairs])
    white_truth = float(np.percentile(want, 99.5))
    white_got = white_truth if calibrated else float(np.percentile(got, 99.5))
    items = []
    for (lv, label), a, b in zip(pairs, want, got):
        pad = np.full((a.shape[0], 2, 3), 255, np.uint8)
        image = np.concatenate([tonemap(a, white=white_truth), pad, tonemap(np.maximum(b, 0), white=white_got)], 1)
        name = save_png(out / f"{prefix}_ingest_lv{lv}.png", image, scale=max(1, 128 // a.shape[0]))
        items.append({"file": name, "lv": lv, "label": label, "calibrated": calibrated})
    return items


def abrdf_image(store: CaptureStore, out: Path, prefix: str) -> dict:
    """The centre texel's ABRDF laid out as in the thesis' Fig. 1.3 (x: light, y: view)."""
    truth = store.group["truth"]["btf"]
    h, w = truth.shape[1:3]
    column = np.asarray(truth[:, h // 2, w // 2, :])                 # (n_lv, 3)
    n_views = store.n_turn * store.n_cam
    image = column.reshape(n_views, store.n_leds, 3)                  # rows: views, cols: lights
    # whole-pixel enlargement to at least ~192 px per axis, as in Fig. 1.3
    scale = tuple(max(1, int(math.ceil(192 / n))) for n in image.shape[:2])
    name = save_png(out / f"{prefix}_abrdf.png", tonemap(image), scale=scale)
    return {"file": name, "texel": [h // 2, w // 2], "shape": [n_views, store.n_leds]}


#: The other reports a demo writes, relative to its folder: (file, what it shows).
RELATED_REPORTS = (("model/report.html", "model database (build-db)"),
                   ("acquisition/report.html", "acquisition evaluation"))


def write_html(path: Path, title: str, summary: dict[str, Any], sections: list[dict[str, Any]],
               links: Sequence[tuple[str, str]] = ()) -> Path:
    """A self-contained HTML page of figure sections (PNG files beside it), linking ``links`` ``(href, label)``."""
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             "<style>body{font-family:sans-serif;max-width:1200px;margin:auto;padding:1em}"
             "figure{display:inline-block;margin:6px;text-align:center;font-size:12px}"
             "img{image-rendering:pixelated;border:1px solid #ccc}"
             "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px}"
             "</style></head><body>", f"<h1>{html.escape(title)}</h1>"]
    if links:
        parts.append("<p>See also: " + " | ".join(f"<a href='{html.escape(href)}'>{html.escape(label)}</a>"
                                                  for href, label in links) + "</p>")
    parts.append("<table>" + "".join(
        f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(json.dumps(v, default=_json_default) if not isinstance(v, str) else v)}</td></tr>"
        for k, v in summary.items()) + "</table>")
    for section in sections:
        parts.append(f"<h2>{html.escape(section['title'])}</h2>")
        if section.get("text"):
            parts.append(f"<p>{html.escape(section['text'])}</p>")
        if section.get("table"):
            header, *rows = section["table"]
            parts.append("<table><tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in header) + "</tr>"
                         + "".join("<tr>" + "".join(f"<td>{html.escape(str(v))}</td>" for v in row) + "</tr>"
                                   for row in rows) + "</table>")
        for fig in section.get("figures", []):
            parts.append(f"<figure><img src='{html.escape(fig['file'])}'><figcaption>"
                         f"{html.escape(fig.get('caption', ''))}</figcaption></figure>")
    parts.append("</body></html>")
    path.write_text("\n".join(parts))
    return path


def _capture_sections(device: Device, store_paths: Sequence[str], stores: Sequence[CaptureStore],
                      fig_dir: Path) -> list[dict[str, Any]]:
    """The report's figures of the simulated captures: the dome, raw frames, ground-truth textures, ABRDFs."""
    sections: list[dict[str, Any]] = [{
        "title": "Dome",
        "text": f"{device.n_cam} cameras, {device.n_leds} lights, {device.n_turn} turntable positions: "
                f"{device.n_lv} light/view pairs; texture {device.texture_shape[0]}x{device.texture_shape[1]}, "
                f"raw region of interest {device.roi_shape[0]}x{device.roi_shape[1]} px.",
        "figures": [{"file": f"report_files/{plot_dome(device, fig_dir / 'dome.png')}",
                     "caption": "lights, cameras and turntable"}],
    }]
    first = stores[0]
    prefix = Path(store_paths[0]).stem
    last_cam = first.n_cam - 1
    raw_views = [(0, 0, 0), (0, last_cam, 0), (0, last_cam, first.n_illum // 2)]
    sections.append({
        "title": f"Raw frames ({prefix})",
        "text": "Each strip is one exposure bracket (short to long) of the raw Bayer mosaic, "
                "black-subtracted and scaled to the sensor range; the sample is the foreshortened "
                "quadrilateral inside the region of interest.",
        "figures": [{"file": f"report_files/{item['file']}",
                     "caption": f"turntable {item['turntable']}, camera {item['camera']}, illumination "
                                f"{item['illumination']}, t = "
                                + ", ".join(f"{x:.3g}" for x in item['exposure_time_s']) + " s"}
                    for item in raw_frame_images(first, fig_dir, prefix, raw_views)],
    })
    tex_figs, abrdf_figs = [], []
    for path, store in zip(store_paths, stores):
        stem = Path(path).stem
        tex_figs += [{"file": f"report_files/{item['file']}", "caption": f"{stem}: {item['label']} (lv {item['lv']})"}
                     for item in texture_images(store, fig_dir, stem)]
        item = abrdf_image(store, fig_dir, stem)
        abrdf_figs.append({"file": f"report_files/{item['file']}",
                           "caption": f"{stem}: texel {tuple(item['texel'])}, {item['shape'][0]} views x {item['shape'][1]} lights"})
    sections.append({"title": "Ground-truth textures", "figures": tex_figs})
    sections.append({"title": "ABRDFs (thesis Fig. 1.3 layout: x = light, y = view)", "figures": abrdf_figs})
    return sections


def _materials_section(materials: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The table of the simulated materials: dynamic range, exposure times, well-exposed fraction."""
    return {
        "title": "Materials",
        "table": [["material", "class", "dynamic range (max/min)", "p99.9/p0.1", "exposures (s)",
                   "well-exposed (min over views)"]] + [
            [m["material_id"], m["class"], f"{m['dynamic_range']:.3g}", f"{m['dynamic_range_p99.9_over_p0.1']:.3g}",
             f"{m['exposure_time_s']['min']:.3g} - {m['exposure_time_s']['max']:.3g}",
             f"{m['well_exposed_fraction_min']:.4f}"] for m in materials],
    }


def _ingest_sections(run: dict[str, Any], store_paths: Sequence[str], stores: Sequence[CaptureStore],
                     fig_dir: Path) -> list[dict[str, Any]]:
    """The ingested BTFs beside the ground truth and their errors (``btf demo``; none for ``btf simulate``)."""
    sections: list[dict[str, Any]] = []
    ingest_figs = []
    for path, store in zip(store_paths, stores):
        btf_path = (run.get("ingest_btf") or {}).get(Path(path).stem)
        if btf_path and store.has_truth:
            ingest_figs += [{"file": f"report_files/{item['file']}",
                             "caption": f"{Path(path).stem}: {item['label']} (lv {item['lv']}): truth | ingested"
                                        f"{' (calibrated, same white point)' if item['calibrated'] else ''}"}
                            for item in ingest_images(store, btf_path, fig_dir, Path(path).stem)]
    if ingest_figs:
        sections.append({"title": "Ingested BTF beside the ground truth (single-LED capture)", "figures": ingest_figs})
    if run.get("ingest"):
        def cell(r: dict, key: str) -> str:
            return f"{r[key]:.4f}" if key in r else "-"

        rows = [(name, label, r) for key, label in (("ingest", "single LED"), ("ingest_multiplexed", "multiplexed"))
                for name, r in run.get(key, {}).items()]
        calibrated = run.get("radiometric") or {}
        sections.append({
            "title": "Ingest (HDR merge, demosaic, rectify, demultiplex, white-standard calibration) against the "
                     "ground truth",
            "text": "Relative L2 error of the ingested BTF against the simulator's truth: 'fitted' after one "
                    "least-squares scale per LED and channel (the chain alone), 'calibrated' as ingested with the "
                    "LED gains measured on the white standard "
                    f"{Path(calibrated['white_standard']).name if calibrated else '(none)'} (chain and calibration).",
            "table": [["material", "illumination", "fitted linear RGB", "fitted log Y", "calibrated linear RGB",
                       "calibrated log Y", "raw MB/s"]] + [
                [name, label, cell(r, "relative_l2_linear"), cell(r, "relative_l2_log_y"),
                 cell(r, "calibrated_relative_l2_linear"), cell(r, "calibrated_relative_l2_log_y"),
                 r.get("raw_mb_per_s", "")] for name, label, r in rows],
        })
    return sections


def _model_section(model: dict[str, Any]) -> dict[str, Any]:
    """``btf demo``'s model database: thesis Table 1 from the leave-one-out evaluation."""
    ks = model["ks"]
    return {
        "title": "Model database (btf build-db): thesis Table 1, leave one out",
        "text": f"log Y relative projection errors [%] of each material on bases merged without it; full "
                f"report with spectra and reconstructions: {model['report_html']}. Trends: "
                + "; ".join(f"{k}: {v}" for k, v in model["trends"].items()),
        "table": [["class", "FMF"] + [f"class k={k}" for k in ks] + [f"global k={k}" for k in ks]] + [
            [cls, f"{row['fmf']:.2f}"] + [("-" if row[f"{kind}_{k}"] is None else f"{row[f'{kind}_{k}']:.2f}")
                                          for kind in ("class", "global") for k in ks]
            for cls, row in model["table_1"].items()],
    }


def _acquisition_section(acquisition: dict[str, Any]) -> dict[str, Any]:
    """``btf demo``'s acquisition evaluation: the thesis' claims with their verdicts and numbers."""
    return {
        "title": "Acquisition (btf evaluate acquisition): the thesis' claims, leave one out",
        "text": f"Scale: {json.dumps(acquisition['scale'])}. Each verdict is computed from the numbers "
                f"beside it; tables, ABRDF images and renderings: {acquisition['report_html']}.",
        "table": [["claim", "verdict", "numbers"]] + [
            [f"({k}) {c['claim']}", c["verdict"], json.dumps(c["numbers"])]
            for k, c in acquisition["claims"].items()],
    }


def simulation_report(out_dir: str | Path, device: Device, store_paths: Sequence[str],
                      run: dict[str, Any]) -> dict[str, Any]:
    """Write ``report.json`` and ``report.html`` (with PNGs) for a simulated database.

    Returns the report dictionary written to ``report.json``.
    """
    out = Path(out_dir)
    fig_dir = out / "report_files"
    fig_dir.mkdir(parents=True, exist_ok=True)
    stores = [open_capture_store(p, mode="r") for p in store_paths]
    materials = []
    for path, store in zip(store_paths, stores):
        stats = material_statistics(store)
        material = store.group["truth"].attrs["material"]
        materials.append({"store": str(path), "material_id": material["material_id"],
                          "class": material["class_name"], "valid": True, **stats})

    sections = _capture_sections(device, store_paths, stores, fig_dir)
    sections.append(_materials_section(materials))
    sections += _ingest_sections(run, store_paths, stores, fig_dir)
    if run.get("model"):
        sections.append(_model_section(run["model"]))
    if run.get("acquisition"):
        sections.append(_acquisition_section(run["acquisition"]))
    report = {"report": "btf-simulate", **run, "device": {
        "name": device.name, "n_cam": device.n_cam, "n_leds": device.n_leds, "n_turn": device.n_turn,
        "n_lv": device.n_lv, "texture_shape": list(device.texture_shape), "roi_shape": list(device.roi_shape)},
        "materials": materials}
    write_json(out / "report.json", report)
    stages = run.get("stages", {})
    summary = {
        **{k: v for k, v in run.items() if not isinstance(v, (dict, list))},
        "device": f"{device.name}: {device.n_lv} light/view pairs, texture {device.texture_shape[0]}x{device.texture_shape[1]}",
        "materials": ", ".join(m["material_id"] for m in materials),
        **{f"{name} stage": ", ".join(f"reused {reused_text(v)}" if k == "reused" else f"{k} {v}"
                                      for k, v in figures.items()) for name, figures in stages.items()},
    }
    links = [(href, label) for href, label in RELATED_REPORTS if (out / href).is_file()]
    write_html(out / "report.html", f"btf-pipeline report: {run.get('command', 'simulate')}", summary, sections,
               links)
    return report
