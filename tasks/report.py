"""Run reports: ``report.json`` for machines, ``report.html`` with PNGs for people.

Figures are made from what the run wrote to disk (capture stores and their
ground truth), so a report shows the data a later stage will read.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from btfcore.capture.view_chain import IngestSettings
from btfcore.simulate.camera import homography_sample_mask
from btfcore.dome import Device
from btfcore.model.colour import REC709_LUMA
from btfcore.simulate.sensor import WELL_EXPOSED
from btfcore.render.tonemap import srgb_encode, tonemap
from tasks.html_report import Cell, write_html
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


#: The execution profile of the run in this process (its file and ``cluster:`` section), set by
#: ``flows.runtime.runtime`` for the run; every report written meanwhile records it (docs/clusters.md).
RUN_PROFILE: dict[str, Any] = {}


def json_text(data: dict[str, Any]) -> str:
    """Plain JSON of a report (numpy values converted, NaN/Inf refused), with the run's ``RUN_PROFILE`` as
    ``"profile"`` during a run."""
    data = {**data, "profile": dict(RUN_PROFILE)} if RUN_PROFILE else data
    return json.dumps(data, indent=2, default=_json_default, allow_nan=False)


def write_json(path: str | Path, data: dict[str, Any]) -> Path:
    """Write :func:`json_text` atomically (a temporary file, then a rename); no kill points, so that a
    stage's reports do not shift the occurrences of its outputs' (:func:`tasks.staging.write_file`)."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json_text(data))
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
    """Figures of one simulated store: dynamic range, exposures, saturation, usable exposures per pixel.

    A raw sample is *usable* when the HDR merge uses it (:func:`btfcore.capture.hdr.merge_linear`):
    below the saturation threshold (``saturation_margin`` of the white level) and, black-subtracted,
    above the noise floor (twice the read noise, at least 1 DN). Counted per frame of the bracket
    before the merge, on the sample's pixels of up to 8 views x 4 illuminations spread over the capture.
    """
    truth = store.group["truth"]["btf"]
    n_lv = truth.shape[0]
    rows = np.unique(np.linspace(0, n_lv - 1, min(n_lv, STAT_ROWS)).astype(int))
    lum = _luminance(np.asarray(truth.get_orthogonal_selection((rows,)), dtype=np.float64))
    p_lo, p_hi = np.percentile(lum, [0.1, 99.9])
    positive = lum[lum > 0]
    times = np.asarray(store.group["exposure_time"][...])
    meta = store.meta
    span = float(meta.white_level - meta.black_level)
    saturated_at = IngestSettings().saturation_margin * meta.white_level
    sensor = meta.sensor
    noise_floor = max(2.0 * sensor.get("read_noise_e", 0.0) / sensor.get("gain_e_per_dn", 1.0), 1.0)
    well, saturated, usable = [], [], []
    views = [(t, c) for t in range(store.n_turn) for c in range(store.n_cam)]
    illuminations = np.unique(np.linspace(0, store.n_illum - 1, min(store.n_illum, 4)).astype(int))
    for t, c in views[:: max(1, len(views) // 8)]:  # up to ~8 views spread over the capture
        mask = homography_sample_mask(store.homography[t, c], store.roi_shape, meta.sample_size_m)
        for i in illuminations:
            frames, _ = store.read_bracket(t, c, int(i))
            level = (frames.astype(np.float64) - meta.black_level) / span
            good = ((level > WELL_EXPOSED[0]) & (level < WELL_EXPOSED[1])).any(axis=0)
            if i == illuminations[0]:
                well.append(float(good[mask].mean()))
                saturated.append(float((frames[0] >= meta.white_level)[mask].mean()))
            usable.append(((frames < saturated_at) & (frames - meta.black_level > noise_floor))[:, mask].sum(axis=0))
    counts = np.concatenate(usable)                                  # usable exposures of each sample pixel
    return {
        "n_lv": int(n_lv),
        # brightest over darkest non-zero luminance of the (noise-free) truth
        "dynamic_range": float(positive.max() / positive.min()) if positive.size else 0.0,
        "dynamic_range_p99.9_over_p0.1": float(p_hi / max(p_lo, 1e-30)),
        "luminance_p0.1": float(p_lo),
        "luminance_p99.9": float(p_hi),
        "exposure_time_s": {"min": float(times.min()), "max": float(times.max())},
        # any frame inside WELL_EXPOSED: 1.0 by construction of the bracket (kept for old readers)
        "well_exposed_fraction_min": float(min(well)),
        "saturated_in_shortest_fraction_max": float(max(saturated)),
        "n_exposures": int(store.n_exp),
        "usable_exposures_per_pixel_mean": float(counts.mean()),
        "single_usable_exposure_fraction": float(np.mean(counts == 1)),
        "no_usable_exposure_fraction": float(np.mean(counts == 0)),
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
                   ("acquisition/report.html", "acquisition evaluation"),
                   ("superres/report.html", "super-resolution evaluation"))


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
    """The table of the simulated materials: dynamic range, exposure times, usable exposures per pixel."""
    n_exp = materials[0].get("n_exposures", "") if materials else ""
    return {
        "title": "Materials",
        "text": [
            "Dynamic range: brightest over darkest luminance of the noise-free ground truth, over all its "
            "light/view pairs (max/min, and the 99.9th over the 0.1st percentile, which ignores a few "
            "extreme texels).",
            f"Usable exposures: of the {n_exp} frames of each bracket, how many the HDR merge uses for a pixel "
            "on the sample (neither saturated nor, black-subtracted, below the noise floor of twice the read "
            "noise), counted per frame before the merge on up to 8 views x 4 illuminations. A pixel with one "
            "usable frame gets that frame's noise alone; the more, the less noise. The former 'well-exposed' "
            "column (a pixel well exposed in some frame) was 1.0 by construction of the exposure brackets "
            "and is no longer shown (report.json keeps well_exposed_fraction_min).",
        ],
        "table": [["material", "class", "dynamic range [max/min]", "dynamic range [p99.9/p0.1]",
                   "shortest exposure [s]", "longest exposure [s]", f"usable exposures [of {n_exp}, mean]",
                   "pixels with one usable exposure [%]", "pixels with none [%]"]] + [
            [m["material_id"], m["class"], m["dynamic_range"], m["dynamic_range_p99.9_over_p0.1"],
             m["exposure_time_s"]["min"], m["exposure_time_s"]["max"], m.get("usable_exposures_per_pixel_mean"),
             100 * m["single_usable_exposure_fraction"] if "single_usable_exposure_fraction" in m else None,
             100 * m["no_usable_exposure_fraction"] if "no_usable_exposure_fraction" in m else None]
            for m in materials],
    }


#: How to read the ingest table's columns (the report's paragraphs; docs/decisions.md, issue 15).
INGEST_TEXT = (
    "Relative L2 errors of the ingested BTF against the simulator's ground truth, on linear RGB and on log "
    "luminance (log(Y + eps), eps = 0.1 % of the mean Y), as fractions (0.1 = 10 %).",
    "'fitted': each LED's and channel's rows are first brought to the truth's scale by one least-squares "
    "factor (48 factors fitted to the truth on the tiny dome): the best any LED calibration could do, so it "
    "measures the chain (HDR merge, demosaic, rectify, demultiplex) alone. 'calibrated': the BTF as ingested "
    "with the LED gains measured on the white standard, no factor fitted: the chain and the calibration "
    "together. The two are close (calibration cost = calibrated - fitted) because the white standard recovers "
    "every LED's gain to about 0.5 %; they are equal only where the calibration is perfect. A large calibration cost means an LED's rows are off as a whole: a bad white standard, or "
    "highlights clipped in every exposure, which the fitted figure hides by scaling that LED up (a sparse "
    "plan's fixed brackets did so in `btf reconstruct --white`: calibrated 0.333 against fitted 0.259, "
    "docs/decisions.md).",
    "Floors: the same pipeline on the same materials, views, brackets and dark-current maps, exposed by two "
    "ideal sensors (fitted errors): 'noise-free' keeps the Bayer mosaic without any noise; 'full RGB' is "
    "noise-free and measures R, G and B at every pixel, so nothing is demosaicked. Read them as shares of the "
    "error: ingest - noise-free is the sensor noise's; noise-free - full RGB is the Bayer mosaic's (aliasing "
    "of texel-scale patterns at about 1.5 camera pixels per texel, the false colour of fine weaves at grazing "
    "angles); full RGB is what remains with a perfect sensor: the cameras' resolution and foreshortening "
    "(a texel covers 1.5 pixels frontally, less at grazing views) and rectification's resampling of the "
    "projected texture to the texel grid. Noise is a small share on this dome (its brackets keep most "
    "pixels well above the read noise); most of the error is the dome's sampling, which a better pipeline "
    "cannot remove, only a higher camera resolution (or super-resolution).",
)


def _ingest_table(run: dict[str, Any]) -> list[list[Any]]:
    """The ingest table: per material and illumination, the errors, the calibration cost and the floors."""
    floors = run.get("ingest_floors") or {}
    header = ["material", "illumination", "fitted linear RGB [1]", "noise-free floor, linear [1]",
              "full-RGB floor, linear [1]", "fitted log Y [1]", "noise-free floor, log Y [1]",
              "full-RGB floor, log Y [1]", "calibrated linear RGB [1]", "calibrated log Y [1]",
              "calibration cost, linear [1]", "raw throughput [MB/s]"]
    rows: list[list[Any]] = [header]
    for key, label in (("ingest", "single LED"), ("ingest_multiplexed", "S-matrix")):
        for name, r in run.get(key, {}).items():
            floor = floors.get(name, {}) if key == "ingest" else {}
            noise_free, full_rgb = floor.get("noise_free", {}), floor.get("full_rgb", {})
            cost = (r["calibrated_relative_l2_linear"] - r["relative_l2_linear"]
                    if "calibrated_relative_l2_linear" in r and "relative_l2_linear" in r else None)
            rows.append([name, label, r.get("relative_l2_linear"), noise_free.get("relative_l2_linear"),
                         full_rgb.get("relative_l2_linear"), r.get("relative_l2_log_y"),
                         noise_free.get("relative_l2_log_y"), full_rgb.get("relative_l2_log_y"),
                         r.get("calibrated_relative_l2_linear"), r.get("calibrated_relative_l2_log_y"), cost,
                         r.get("raw_mb_per_s")])
    return rows


def floor_shares(run: dict[str, Any], metric: str = "relative_l2_linear") -> dict[str, float] | None:
    """The mean over the single-LED materials with floors of the fitted error and its shares:
    ``noise`` (error - noise-free floor), ``mosaic`` (noise-free - full-RGB floor) and ``sampling``
    (the full-RGB floor); None without floors."""
    floors = run.get("ingest_floors") or {}
    rows = [(r[metric], floors[name]["noise_free"][metric], floors[name]["full_rgb"][metric])
            for name, r in (run.get("ingest") or {}).items() if name in floors and metric in r]
    if not rows:
        return None
    error, noise_free, full_rgb = (float(np.mean(x)) for x in zip(*rows))
    return {"error": error, "noise": error - noise_free, "mosaic": noise_free - full_rgb, "sampling": full_rgb}


def floor_shares_text(run: dict[str, Any]) -> str:
    """One sentence with the shares of :func:`floor_shares` on linear RGB and log Y, in percent."""
    parts = []
    for metric, label in (("relative_l2_linear", "linear RGB"), ("relative_l2_log_y", "log Y")):
        shares = floor_shares(run, metric)
        if shares:
            parts.append(f"{label}: error {100 * shares['error']:.1f} % = noise {100 * shares['noise']:.1f} % + "
                         f"Bayer mosaic {100 * shares['mosaic']:.1f} % + sampling and resampling "
                         f"{100 * shares['sampling']:.1f} %")
    return ("Mean over the materials, " + "; ".join(parts) + ".") if parts else ""


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
        calibrated = run.get("radiometric") or {}
        white = Path(calibrated["white_standard"]).name if calibrated.get("white_standard") else "(none)"
        sections.append({
            "title": "Ingest (HDR merge, demosaic, rectify, demultiplex, white-standard calibration) against the "
                     "ground truth, beside its floors",
            "text": [*INGEST_TEXT, f"White standard: {white}. The floors are of the single-LED captures. "
                     + floor_shares_text(run)],
            "table": _ingest_table(run),
        })
    return sections


def _model_section(model: dict[str, Any]) -> dict[str, Any]:
    """``btf demo``'s model database: thesis Table 1 from the leave-one-out evaluation."""
    ks = model["ks"]
    trends = model["trends"]
    return {
        "title": "Model database (btf build-db): thesis Table 1, leave one out",
        "text": [f"log Y relative projection errors in % of each material on bases merged without it "
                 f"(paper 1 (den Brok et al.) §4.1.1); the full report, with spectra and reconstructions: "
                 f"model/report.html.",
                 "Trends: errors fall with k: " + ("yes" if trends.get("error_falls_with_k") else "no")
                 + f"; class bases beat the global one in {trends.get('class_beats_global')}."],
        "table": [["class", "FMF [%]"] + [f"class k={k} [%]" for k in ks] + [f"global k={k} [%]" for k in ks]] + [
            [cls, row["fmf"]] + [row[f"{kind}_{k}"] for kind in ("class", "global") for k in ks]
            for cls, row in model["table_1"].items()],
    }


def _acquisition_section(acquisition: dict[str, Any]) -> dict[str, Any]:
    """``btf demo``'s acquisition evaluation: the thesis' claims with their verdicts and numbers."""
    return {
        "title": "Acquisition (btf evaluate acquisition): the thesis' claims, leave one out",
        "text": "Each verdict is computed from the numbers beside it; tables, ABRDF images and renderings: "
                "acquisition/report.html.",
        "tables": [[["scale", "value"]] + [[label, value] for label, value in acquisition["scale"].items()],
                   [["claim", "verdict", "numbers"]] + [
                       [f"({k}) {c['claim']}", c["verdict"], c["numbers"]]
                       for k, c in acquisition["claims"].items()]],
    }


def _superres_section(superres: dict[str, Any]) -> dict[str, Any]:
    """``btf demo``'s super-resolution step: the SR paper's Table 2 means, both protocols, and the crops."""
    rows: list[Any] = [["protocol", "method", "mRMSE [BTF units]", "mPSNR [dB]", "mRE [%]"]]
    for protocol, label in (("paper", "paper: 1/2 -> 1 vs measured"), ("exact", "exact: 1 -> 2 vs 2x truth")):
        rows += [[label, m, v["mrmse"], v["mpsnr"], v["mre"]] for m, v in superres["means"][protocol].items()]
    verdict = superres["verdicts"]
    return {"title": "Super-resolution (btf evaluate superres at the demo's scale)",
            "text": [f"Means over the test materials; the ESPCN (HDR normalisation: {superres['normalisation']}) "
                     f"{'beats' if verdict['espcn_beats_dong_and_bicubic'] else 'does not beat'} bicubic and Dong et "
                     "al. on every test material in both mPSNR and mRE. Per material, the regions' scores and "
                     "scale invariance: superres/report.html."],
            "table": rows, "figures": superres["figures"]}


#: What each of the demo's stages does, for the report (keys of ``run["stages"]``).
STAGE_NAMES = {
    "simulate": "simulate the materials (single LED)",
    "simulate white standard": "simulate the white standard",
    "ingest white standard": "ingest the white standard",
    "ingest": "ingest the materials, calibrated",
    "ingest floors": "ingest floors (noise-free and full-RGB sensors)",
    "simulate multiplexed": "simulate the S-matrix captures",
    "ingest multiplexed": "ingest the S-matrix captures",
    "build-db": "build the model database",
    "super-resolution": "super-resolution: train the ESPCN, score it against bicubic and Dong et al.",
    "evaluate acquisition": "evaluate acquisition",
    "report": "write this report",
}


def _stages_section(stages: dict[str, Any], total_s: float | None = None) -> dict[str, Any]:
    """The run's stages: what each did, how long it took and what it reused from an earlier run."""
    rows: list[list[Any]] = [["stage", "what it does", "time [s]", "share of the stages' time [%]", "reused"]]
    for name, figures in stages.items():
        seconds = figures.get("seconds")
        rows.append([name, STAGE_NAMES.get(name, name), seconds,
                     100 * seconds / total_s if total_s and seconds is not None else None,
                     reused_text(figures["reused"]) if figures.get("reused") else None])
    return {"title": "Stages", "table": rows}


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
    if run.get("superres"):
        sections.append(_superres_section(run["superres"]))
    if run.get("acquisition"):
        sections.append(_acquisition_section(run["acquisition"]))
    report = {"report": "btf-simulate", **run, "device": {
        "name": device.name, "n_cam": device.n_cam, "n_leds": device.n_leds, "n_turn": device.n_turn,
        "n_lv": device.n_lv, "texture_shape": list(device.texture_shape), "roi_shape": list(device.roi_shape)},
        "materials": materials}
    if run.get("ingest_floors"):
        report["ingest_floor_shares"] = {metric: floor_shares(run, metric)
                                         for metric in ("relative_l2_linear", "relative_l2_log_y")}
    write_json(out / "report.json", report)
    stages = run.get("stages", {})
    if stages:
        sections.insert(0, _stages_section(stages, sum(f.get("seconds") or 0.0 for f in stages.values())))
    summary = {
        "command": f"btf {run.get('command', 'simulate')}",
        "output folder": run.get("out_dir", str(out)),
        "device": f"{device.name}: {device.n_cam} cameras x {device.n_leds} LEDs x {device.n_turn} turntable "
                  f"positions = {device.n_lv:,} light/view pairs, texture {device.texture_shape[0]} x "
                  f"{device.texture_shape[1]} texels",
        "materials": ", ".join(m["material_id"] for m in materials),
        **({"stages' time": Cell(round(sum(f.get("seconds") or 0.0 for f in stages.values()), 1), unit="s")}
           if stages else {}),
    }
    links = [(href, label) for href, label in RELATED_REPORTS if (out / href).is_file()]
    write_html(out / "report.html", f"btf-pipeline report: {run.get('command', 'simulate')}", summary, sections,
               links)
    return report
