"""`report.json` and `report.html` of `btf build-db`: spectra, thesis Table 1 (paper 1 (den Brok et al.)
§4.1.1), reconstructions; cells against the trend checks' expectation flagged with the reason."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from btfcore.model.colour import to_log_yuv
from btfcore.render.tonemap import tonemap
from tasks.model import Material, ModelSettings, merge_bases
from tasks.html_report import Cell
from tasks.report import pyplot, save_figure, save_png, write_html, write_json

#: The other reports of a demo, relative to the model database's folder: (file, what it shows).
RELATED_REPORTS = (("../report.html", "demo report (simulation, ingest and its floors)"),
                   ("../acquisition/report.html", "acquisition evaluation"))


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
            scale = tuple(max(1, int(math.ceil(256 / n))) for n in pair[0].shape)
            file = save_png(out / f"model_{m.material_id}_{name}.png", image, scale=scale)
            what = (f"centre texel's ABRDF (x: light, y: view)" if name == "abrdf"
                    else f"texture of light/view pair {row}")
            figures.append({"file": f"report_files/{file}",
                            "caption": f"{m.material_id}: {what}, measured | projected on the {cls} basis "
                                       f"without it (k = {k})"})
    return figures


def table_1_rows(summary: dict[str, Any]) -> list[Any]:
    """Thesis Table 1 as report rows (header first, errors in %), each cell the trend checks would not
    expect flagged with the reason (:func:`trend_flag`)."""
    ks, table = summary["ks"], summary["table_1"]
    header = ["class", "FMF [%]"] + [f"{kind} k={k} [%]" for kind in ("class", "global", "ABTF") for k in ks]
    rows: list[Any] = [header]
    for cls, row in table.items():
        cells: list[Any] = [cls, row["fmf"]]
        for kind in ("class", "global", "abtf"):
            for i, k in enumerate(ks):
                reason = trend_flag(row, kind, ks, i)
                value = row[f"{kind}_{k}"]
                cells.append(value if reason is None else Cell(value, flag=reason))
        rows.append(cells)
    return rows


def trend_flag(row: dict[str, Any], kind: str, ks: list[int], i: int) -> str | None:
    """Why the Table-1 cell ``(kind, ks[i])`` of a class is above what :func:`trend_checks` expects, or None:
    the error rises with k (it should fall), or a class basis loses to the global one at the same k."""
    value = row[f"{kind}_{ks[i]}"]
    if value is None:
        return None
    before = row[f"{kind}_{ks[i - 1]}"] if i else None
    if before is not None and value > before + 1e-9:
        return (f"{kind} basis error rises from {before:.3g} % at k = {ks[i - 1]} to {value:.3g} % at k = {ks[i]}; "
                "the trend check expects it to fall with k")
    global_value = row.get(f"global_{ks[i]}")
    if kind == "class" and global_value is not None and value >= global_value:
        return (f"class basis ({value:.3g} %) is not better than the global one ({global_value:.3g} %) at "
                f"k = {ks[i]}; the trend check expects the class basis to win")
    return None


def model_report(out_dir: str | Path, summary: dict[str, Any], settings: ModelSettings,
                 links: list[tuple[str, str]] | None = None) -> dict[str, Any]:
    """Write ``report.json`` and ``report.html`` of a model database build into ``out_dir``.

    ``links``: ``(href, label)`` of other reports to link; by default those of :data:`RELATED_REPORTS`
    that exist (the demo passes the ones it is about to write).
    """
    out = Path(out_dir)
    figs = out / "report_files"
    figs.mkdir(parents=True, exist_ok=True)
    materials = [Material(**{**m, "texture_shape": tuple(m["texture_shape"])}) for m in summary["materials"]]
    ks = summary["ks"]
    table = summary["table_1"]
    trends = trend_checks(summary)
    sections = [
        {"title": "Singular value spectra", "figures": [{"file": f"report_files/{_plot_spectra(summary, figs / 'model_spectra.png')}",
                                                          "caption": "merged log Y bases per class and global"}]},
        {"title": "Projection error against k (leave one out)",
         "figures": [{"file": f"report_files/{_plot_errors(summary, figs / 'model_errors.png')}",
                      "caption": "mean over each class' materials, each projected on bases merged without it"}]},
        {"title": "Thesis Table 1: log Y relative projection errors [%]",
         "text": ["Each material is projected on bases merged without it (per class: its class; global: all "
                  "classes) with its first k vectors, and the relative L2 error of its log luminance is averaged "
                  "over the class, in % (paper 1 (den Brok et al.) §4.1.1); FMF: its own per-material basis (k = "
                  f"{summary['leave_one_out'][0]['fmf_k']}); ABTF: {settings.patch}x{settings.patch} patches on "
                  "the class' patch basis.",
                  "Trend checks: the errors fall with k: " + ("yes" if trends["error_falls_with_k"] else "no")
                  + f"; class bases beat the global one in {trends['class_beats_global']}. A cell in red is "
                  "above what these checks expect (its reason in the footnote)."],
         "table": table_1_rows(summary)},
        {"title": "Reconstructions", "figures": _reconstructions(summary["model"], materials, settings, ks[-1], figs)},
    ]
    report = {"report": "btf-build-db", **{k: v for k, v in summary.items() if k != "materials"},
              "materials": summary["materials"], "trends": trends, "incremental": incremental(summary["fits"])}
    write_json(out / "report.json", report)
    classes = sorted(table)
    if links is None:
        links = [(href, label) for href, label in RELATED_REPORTS if (out / href).is_file()]
    write_html(out / "report.html", "btf-pipeline report: build-db",
               {"materials": len(materials), "classes": ", ".join(classes), "model store": summary["model"],
                "fitted in this run": report["incremental"]["summary"],
                "basis vectors kept (k)": ", ".join(f"{b}: {d.get('__global__', max(d.values()))}"
                                                    for b, d in summary["k"].items())},
               sections, links)
    return report


def incremental(fits: list[dict[str, Any]]) -> dict[str, Any]:
    """What a build fitted and what it reused (``fits``: one ``{"material", "bases"}`` per material, a
    reused basis marked ``"reused"``), with one line that says it: a rebuild of an unchanged database
    fits nothing new."""
    fitted = [f["material"] for f in fits if set(f["bases"].values()) != {"reused"}]
    reused = [f["material"] for f in fits if set(f["bases"].values()) == {"reused"}]
    line = (f"nothing new to fit: the bases of all {len(reused)} materials were reused" if not fitted
            else f"fitted {len(fitted)} of {len(fits)} materials ({', '.join(fitted)}); reused {len(reused)}")
    return {"fitted": fitted, "reused": reused, "summary": line}


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
