"""`report.json` and `report.html` of `btf build-db`: spectra, thesis Table 1, reconstructions."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from btfcore.model.colour import to_log_yuv
from btfcore.render.tonemap import tonemap
from tasks.model import Material, ModelSettings, merge_bases
from tasks.report import pyplot, save_figure, save_png, write_html, write_json


def _plot_spectra(summary: dict[str, Any], path: Path) -> str:
    fig, ax = pyplot().subplots(figsize=(7, 4))
    for name, sigma in sorted(summary["spectra"].items()):
        s = np.asarray(sigma)
        ax.semilogy(np.arange(1, s.size + 1), s / s[0], lw=2.5 if name == "__global__" else 1.2,
                    label="global" if name == "__global__" else name)
    ax.set_xlabel("basis vector")
    ax.set_ylabel("singular value / first")
    ax.set_title("log Y bases: singular value spectra (merged)")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def _plot_errors(summary: dict[str, Any], path: Path) -> str:
    fig, ax = pyplot().subplots(figsize=(7, 4))
    classes = sorted({r["class"] for r in summary["leave_one_out"]})
    for i, cls in enumerate(classes):
        rows = [r for r in summary["leave_one_out"] if r["class"] == cls]
        n = min(min(len(r["class_basis"]), len(r["global_basis"])) for r in rows)
        k = np.arange(1, n + 1)
        colour = f"C{i}"
        ax.plot(k, 100 * np.mean([r["class_basis"][:n] for r in rows], axis=0), c=colour, label=f"{cls}: class")
        ax.plot(k, 100 * np.mean([r["global_basis"][:n] for r in rows], axis=0), c=colour, ls="--",
                label=f"{cls}: global")
    ax.set_xscale("log", base=2)
    ax.set_xlabel("number of basis ABRDFs k")
    ax.set_ylabel("log Y relative projection error [%]")
    ax.set_title("held-out materials projected on bases fitted without them")
    ax.legend(fontsize=7, ncol=2)
    return save_figure(fig, path)


def _reconstructions(model_path: str, materials: list[Material], settings: ModelSettings, k: int,
                     out: Path) -> list[dict[str, str]]:
    """For one material per class: its centre ABRDF and one texture, measured beside their projection on
    the class basis fitted without it (log Y shown as luminance)."""
    group = zarr.open_group(model_path, mode="r", zarr_format=3)
    figures = []
    for cls in sorted({m.cls for m in materials}):
        m = next(x for x in materials if x.cls == cls)
        U = merge_bases(group, materials, settings, exclude=m.material_id, store=False,
                        bases=("log_y",))["log_y"][cls].U[:, :k]
        btf = zarr.open_group(m.path, mode="r", zarr_format=3)
        n_turn, n_cam, n_leds = btf.attrs["turntable_cameras_leds"]
        h, w = m.texture_shape
        log_y = to_log_yuv(np.asarray(btf["btf"][...]))[..., 0].reshape(m.n_lv, -1).astype(np.float64)
        recon = U @ (U.T @ log_y)
        column = h // 2 * w + w // 2
        abrdf = [np.exp(x[:, column]).reshape(n_turn * n_cam, n_leds) for x in (log_y, recon)]
        row = int(np.argmax(log_y.mean(axis=1)))
        texture = [np.exp(x[row]).reshape(h, w) for x in (log_y, recon)]
        for name, pair in (("abrdf", abrdf), ("texture", texture)):
            white = float(np.percentile(pair[0], 99.5))
            pad = np.full((pair[0].shape[0], 2), 255, np.uint8)
            image = np.concatenate([tonemap(pair[0], white=white), pad, tonemap(pair[1], white=white)], axis=1)
            scale = tuple(max(1, int(math.ceil(160 / n))) for n in pair[0].shape)
            file = save_png(out / f"model_{m.material_id}_{name}.png", image, scale=scale)
            what = (f"centre texel's ABRDF (x: light, y: view)" if name == "abrdf"
                    else f"texture of light/view pair {row}")
            figures.append({"file": f"report_files/{file}",
                            "caption": f"{m.material_id}: {what}, measured | projected on the {cls} basis "
                                       f"without it (k = {k})"})
    return figures


def model_report(out_dir: str | Path, summary: dict[str, Any], settings: ModelSettings) -> dict[str, Any]:
    """Write ``report.json`` and ``report.html`` of a model database build into ``out_dir``."""
    out = Path(out_dir)
    figs = out / "report_files"
    figs.mkdir(parents=True, exist_ok=True)
    materials = [Material(**{**m, "texture_shape": tuple(m["texture_shape"])}) for m in summary["materials"]]
    ks = summary["ks"]
    table = summary["table_1"]
    header = ["class", "FMF"] + [f"class k={k}" for k in ks] + [f"global k={k}" for k in ks] + \
             [f"ABTF k={k}" for k in ks]
    rows = [[cls, f"{row['fmf']:.2f}"] + [("-" if row[f"{kind}_{k}"] is None else f"{row[f'{kind}_{k}']:.2f}")
                                          for kind in ("class", "global", "abtf") for k in ks]
            for cls, row in table.items()]
    trends = trend_checks(summary)
    sections = [
        {"title": "Singular value spectra", "figures": [{"file": f"report_files/{_plot_spectra(summary, figs / 'model_spectra.png')}",
                                                          "caption": "merged log Y bases per class and global"}]},
        {"title": "Projection error against k (leave one out)",
         "figures": [{"file": f"report_files/{_plot_errors(summary, figs / 'model_errors.png')}",
                      "caption": "mean over each class' materials, each projected on bases merged without it"}]},
        {"title": "Thesis Table 1: log Y relative projection errors [%]",
         "text": "Each material is projected on bases merged without it (per class: its class; global: all "
                 "classes) with its first k vectors; FMF: its own per-material basis (k = "
                 f"{summary['leave_one_out'][0]['fmf_k']}); ABTF: {settings.patch}x{settings.patch} patches on "
                 "the class' patch basis. Trends: " + "; ".join(f"{k}: {v}" for k, v in trends.items()),
         "table": [header] + rows},
        {"title": "Reconstructions", "figures": _reconstructions(summary["model"], materials, settings, ks[-1], figs)},
    ]
    report = {"report": "btf-build-db", **{k: v for k, v in summary.items() if k != "materials"},
              "materials": summary["materials"], "trends": trends}
    write_json(out / "report.json", report)
    classes = sorted(table)
    write_html(out / "report.html", "btf-pipeline report: build-db",
               {"materials": len(materials), "classes": ", ".join(classes), "model": summary["model"],
                "bases (k)": ", ".join(f"{b}: {d.get('__global__', max(d.values()))}" for b, d in summary["k"].items())},
               sections)
    return report


def trend_checks(summary: dict[str, Any]) -> dict[str, Any]:
    """The two Table-1 trends of issue 4: errors fall with k; class bases beat the global one at equal k."""
    loo = summary["leave_one_out"]
    falls = all(np.all(np.diff(r[key]) <= 1e-12) for r in loo for key in ("class_basis", "global_basis"))
    wins, total = 0, 0
    for k in summary["ks"]:
        for cls, row in summary["table_1"].items():
            if row[f"class_{k}"] is not None and row[f"global_{k}"] is not None:
                total += 1
                wins += row[f"class_{k}"] < row[f"global_{k}"]
    return {"error_falls_with_k": bool(falls), "class_beats_global": f"{wins} of {total} (class, k) cells"}
