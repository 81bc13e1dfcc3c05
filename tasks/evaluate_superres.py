"""``btf evaluate superres``: the SR paper's Table 2 on simulated leather and cloth, two protocols, scale invariance.

What it measures (docs/super-resolution.md):

* **Paper protocol** (SR paper §5.1): the measured regions of interest are the
  reference; down-sampled once they are the input, twice the training input. A
  network learns 1/4 -> 1/2 and is applied 1/2 -> 1; the result, rectified at
  the texture size, is compared with the ingested BTF (the measured regions
  rectified). Dong et al. (SR paper §3.4) up-sample the eigentextures of the
  BTF rectified from the half-resolution regions; bicubic interpolation of the
  regions is the floor.
* **Exact protocol** (beyond the paper): a network learns 1/2 -> 1 and is
  applied 1 -> 2; the result, rectified at twice the texture size, is
  compared with the simulator's exact 2x ground truth (``truth/btf_2x``) and
  the regions with their 2x truth (:func:`tasks.simulate.roi_truth`). Each
  (light, channel) is first brought to the truth's unit by the least-squares
  factor that maps the ingested 1x BTF to the 1x truth, the same factor for
  every method.
* **Scale invariance** (SR paper §5.5): the network trained 1/4 -> 1/2 also
  applied 1 -> 2, against the one trained 1/2 -> 1.
* **Normalisation** of HDR input (not stated by the paper): ``log`` and
  ``scale`` networks, chosen on the validation materials under the paper
  protocol (no truth needed), both reported.

Metrics are the SR paper's eqs. (8)-(10) (:mod:`btfcore.metrics`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from btfcore.metrics import mpsnr, mre, mrmse
from btfcore.superres.regions import rectify_regions, scale_homography, upsample_regions
from btfcore.superres.scaling import area_downsample
from tasks.buffers import heap_arrays
from tasks.faults import kill_point
from tasks.ingest import led_scale
from tasks.report import write_json
from tasks.superres import SUPERRES_FACTOR, load_model, one_torch_thread, view_rows, with_regions

__all__ = ["METHODS", "NORMALISATIONS", "SuperresEvaluationConfig", "choose", "mean_table", "model_path",
           "scores", "test_material", "validation_material", "verdicts"]

#: The methods of the SR paper's Table 2 and the floor, in the report's order.
METHODS: tuple[str, ...] = ("bicubic", "dong", "espcn")
NORMALISATIONS: tuple[str, ...] = ("log", "scale")
#: Version of a test material's cached scores (``MODELS_DIR/<material>.scores.json``): bump when they change.
SCORES_VERSION = 1


@dataclass(frozen=True)
class SuperresEvaluationConfig:
    """The scale of ``btf evaluate superres`` (defaults: see docs/super-resolution.md, "Scale").

    ``materials_per_class`` leathers and as many cloths on ``device`` with ``camera_scale`` times its
    pixels and ``texture_size`` texels. Every validation and test material trains its own networks on
    118 of its rows (the SR paper's images per material) or ``fraction`` of them (the capture's own
    down-sampled regions); per class the first ``n_train``
    materials also train one network for the others (the SR paper's split, scored beside it), the next
    ``n_validation`` choose the normalisation and Dong's alpha (without any: the default normalisation
    and alpha), the rest are the test materials.
    """

    device: str = "tiny"
    camera_scale: int = 2
    texture_size: int = 96
    materials_per_class: int = 5
    n_train: int = 2
    n_validation: int = 1
    seed: int = 0
    fraction: float | None = None
    max_epochs: int = 20
    dong_rank: int = 300
    dong_alphas: tuple[float, ...] = (1e-3, 3e-3, 1e-2, 3e-2, 1e-1)

    def __post_init__(self) -> None:
        if self.materials_per_class < self.n_train + self.n_validation + 1 or min(self.n_train, self.n_validation) < 0:
            raise ValueError(f"materials_per_class {self.materials_per_class} must leave at least one test material "
                             f"per class after {self.n_train} training and {self.n_validation} validation "
                             "material(s)")
        if self.camera_scale < 1 or self.texture_size < 8 or self.texture_size % 2:
            raise ValueError("camera_scale must be >= 1 and texture_size an even number >= 8, got "
                             f"{self.camera_scale} and {self.texture_size}")
        if self.fraction is not None and not 0 < self.fraction <= 1:
            raise ValueError(f"fraction must lie in (0, 1], got {self.fraction}")

    def with_seed(self, seed: int) -> "SuperresEvaluationConfig":
        return dataclasses.replace(self, seed=seed)

    def simulation(self) -> Any:
        """The :class:`tasks.simulate.SimulationConfig` of the evaluation's database."""
        from tasks.simulate import SimulationConfig

        return SimulationConfig(device=self.device, n_materials=2 * self.materials_per_class, seed=self.seed,
                                classes=("leather", "cloth"), texture_size=self.texture_size,
                                camera_scale=self.camera_scale)

    def split(self, names: list[str]) -> dict[str, list[str]]:
        """``{"train", "validation", "test"}`` -> store names, per class in order, classes interleaved."""
        parts: dict[str, list[str]] = {"train": [], "validation": [], "test": []}
        for cls in ("leather", "cloth"):
            mine = sorted(n for n in names if n.split("-", 1)[-1].startswith(cls))
            parts["train"] += mine[:self.n_train]
            parts["validation"] += mine[self.n_train:self.n_train + self.n_validation]
            parts["test"] += mine[self.n_train + self.n_validation:]
        return parts

    def to_json(self) -> dict[str, Any]:
        return {**asdict(self), "dong_alphas": list(self.dong_alphas)}

    def training(self) -> dict[str, Any]:
        """What each material's own networks are trained with (:func:`own_models`)."""
        return {"fraction": self.fraction, "seed": self.seed, "max_epochs": self.max_epochs,
                "compare_normalisations": self.n_validation > 0}


#: ``btf demo``'s super-resolution step: the tiny dome as simulated (72 x 72 regions, 32 x 32 texels), one
#: leather and one cloth, each training its own networks (the default normalisation only) on 118 of its 192 rows for 4 epochs.
DEMO_SUPERRES = SuperresEvaluationConfig(camera_scale=1, texture_size=32, materials_per_class=1, n_train=0,
                                         n_validation=0, max_epochs=4)


def scores(reference: np.ndarray, estimate: np.ndarray) -> dict[str, float]:
    """mRMSE, mPSNR [dB] and mRE [%] of SR paper eqs. (8)-(10)."""
    return {"mrmse": mrmse(reference, estimate), "mpsnr": mpsnr(reference, estimate), "mre": mre(reference, estimate)}


def _in_truth_units(x: np.ndarray, scale: np.ndarray) -> np.ndarray:
    n_leds = scale.shape[0]
    return (x.reshape(-1, n_leds, *x.shape[1:]) * scale[None, :, None, None, :].astype(np.float32)).reshape(x.shape)


def _views(store: Any) -> list[tuple[int, int, slice, np.ndarray, np.ndarray]]:
    """``(t, c, rows, regions, homography)`` of every view of a store with regions (read view by view)."""
    n_turn, n_cam, _ = store.attrs["turntable_cameras_leds"]
    homography = store.homography
    return [(t, c, view_rows(store, t, c), np.asarray(store.roi[view_rows(store, t, c)], dtype=np.float32),
             homography[t, c]) for t in range(n_turn) for c in range(n_cam)]


def _half_scale(store: Any, views: list, networks: dict[str, Any]) -> dict[str, np.ndarray]:
    """The paper protocol's estimates of the 1x BTF from the regions down-sampled once: bicubic and the
    ``networks`` (up-sampled, rectified at 1x) and the half-resolution BTF Dong's method starts from."""
    h, w = store.texture_shape
    s = float(store.attrs["sample_size_m"])
    out = {name: np.empty((store.n_lv, h, w, 3), np.float32) for name in ["bicubic", *networks]}
    out["half"] = np.empty((store.n_lv, h // 2, w // 2, 3), np.float32)
    for _, _, rows, regions, H in views:
        half = area_downsample(regions, 2)
        if half.shape[1] * 2 != regions.shape[1] or half.shape[2] * 2 != regions.shape[2]:
            raise ValueError(f"{store.path}: regions of {regions.shape[1]} x {regions.shape[2]} pixels; the paper "
                             "protocol needs an even size")
        out["half"][rows] = rectify_regions(half, scale_homography(H, 0.5), (h // 2, w // 2), s)
        out["bicubic"][rows] = rectify_regions(upsample_regions(half, method="bicubic"), H, (h, w), s)
        for name, net in networks.items():
            out[name][rows] = rectify_regions(upsample_regions(half, model=net), H, (h, w), s)
    return out


def own_models(btf_path: str, models_dir: str, normalisations: tuple[str, ...], protocols: tuple[str, ...],
               training: dict[str, Any]) -> dict[str, Any]:
    """Networks trained on the material's own regions (``training``: ``fraction``, ``seed``, ``max_epochs``),
    one per protocol and normalisation, kept as ``MODELS_DIR/<material>-<protocol>-<normalisation>.pt``
    (:func:`tasks.superres.train_model` reuses a file of the same training); ``{key: (model, summary)}``
    keyed ``"<protocol>_<normalisation>"``."""
    from btfcore.superres.espcn import EspcnConfig
    from btfcore.superres.training import TrainingSettings
    from tasks.superres import train_model

    settings = TrainingSettings(max_epochs=training["max_epochs"], seed=training["seed"])
    out = {}
    for protocol in protocols:
        for norm in normalisations:
            path = Path(models_dir) / f"{Path(btf_path).stem}-{protocol}-{norm}.pt"
            summary = train_model([btf_path], path, protocol=protocol, fraction=training["fraction"],
                                  config=EspcnConfig(normalisation=norm), settings=settings)
            brief = {k: summary[k] for k in ("protocol", "patches", "best_epoch", "samples_per_second", "seconds",
                                             "reused")}
            out[f"{protocol}_{norm}"] = (load_model(path).model, brief)
    return out


def validation_material(btf_path: str, alphas: list[float], dong_rank: int, models_dir: str,
                        training: dict[str, Any]) -> dict[str, Any]:
    """Scores that choose the normalisation (paper protocol, networks trained on the material's own regions)
    and Dong's alpha on one material; no ground truth is used."""
    from btfcore.superres.dong import dong_eigentextures

    one_torch_thread()
    store = with_regions(btf_path)
    reference = np.asarray(store.btf[...], dtype=np.float32)
    trained = own_models(btf_path, models_dir, NORMALISATIONS, ("paper",), training)
    est = _half_scale(store, _views(store), {norm: trained[f"paper_{norm}"][0] for norm in NORMALISATIONS})
    result = {"espcn_mre": {norm: scores(reference, est[norm])["mre"] for norm in NORMALISATIONS},
              "bicubic_mre": scores(reference, est["bicubic"])["mre"], "dong_mre": {},
              "training": {k: v[1] for k, v in trained.items()}}
    for alpha in alphas:
        dong = dong_eigentextures(est["half"], rank=dong_rank, factor=2, alpha=alpha)
        result["dong_mre"][str(alpha)] = scores(reference, dong)["mre"]
    return result


@heap_arrays()
def test_material(btf_path: str, capture_path: str, others: str | None, normalisation: str, alpha: float,
                  dong_rank: int, device_json: dict[str, Any], figures_dir: str, models_dir: str,
                  training: dict[str, Any]) -> dict[str, Any]:
    """Every score of one test material: both protocols, the regions' 2x truth, scale invariance, crops.

    The ESPCN is trained on the material's own regions (``training``): 1/2 -> 1 (``exact``) with the chosen
    ``normalisation``, 1/4 -> 1/2 (``paper``) with both. ``others``: a model file trained on other materials
    (the SR paper's split; scored as ``espcn_others`` in the exact protocol), or None. ``device_json``: the
    simulated dome (``Device.to_json``).
    """
    from btfcore.dome import Device
    from btfcore.superres.dong import dong_eigentextures
    from tasks.simulate import roi_truth
    from tasks.stores import open_capture_store

    one_torch_thread()
    start = time.perf_counter()
    store, capture = with_regions(btf_path), open_capture_store(capture_path)
    key = _scores_key(store, capture, others, normalisation, alpha, dong_rank, training)
    cached = Path(models_dir) / f"{Path(btf_path).stem}.scores.json"
    if cached.is_file():
        previous = json.loads(cached.read_text())
        if previous.get("key") == key and all((Path(figures_dir).parent / f["file"]).is_file()
                                              for f in previous["result"]["figures"]):
            return {**previous["result"], "reused": True}
    device = Device.from_json(device_json)
    n_leds = int(store.attrs["turntable_cameras_leds"][2])
    h, w = store.texture_shape
    s = float(store.attrs["sample_size_m"])
    btf1 = np.asarray(store.btf[...], dtype=np.float32)
    unit = led_scale(btf1, capture.truth["btf"][...], n_leds)
    truth2 = np.asarray(capture.truth["btf_2x"][...], dtype=np.float32)
    views = _views(store)
    compared = NORMALISATIONS if training.get("compare_normalisations", True) else (normalisation,)
    trained = {**own_models(btf_path, models_dir, (normalisation,), ("exact",), training),
               **own_models(btf_path, models_dir, compared, ("paper",), training)}
    nets = {"espcn": trained[f"exact_{normalisation}"][0], "espcn_twice": trained[f"paper_{normalisation}"][0]}
    if others is not None:
        nets["espcn_others"] = load_model(others).model
    paper_nets = {norm: trained[f"paper_{norm}"][0] for norm in compared}
    # exact protocol: 1 -> 2 against the simulator's 2x truth, regions and textures
    est2 = {m: np.empty((store.n_lv, 2 * h, 2 * w, 3), np.float32) for m in ("bicubic", *nets)}
    roi_scores: dict[str, list[dict[str, float]]] = {"bicubic": [], "espcn": []}
    for t, c, rows, regions, H in views:
        H2 = scale_homography(H, SUPERRES_FACTOR)
        truth_roi = roi_truth(device, truth2[rows], t, c, SUPERRES_FACTOR)
        for name, kw in (("bicubic", {"method": "bicubic"}), *((n, {"model": net}) for n, net in nets.items())):
            up = upsample_regions(regions, **kw)
            est2[name][rows] = rectify_regions(up, H2, (2 * h, 2 * w), s)
            if name in roi_scores:
                roi_scores[name].append(scores(truth_roi, _in_truth_units(up, unit)))
    est2["dong"] = dong_eigentextures(btf1, rank=dong_rank, factor=2, alpha=alpha)
    exact_scores = {m: scores(truth2, _in_truth_units(est2[m], unit)) for m in est2}
    # paper protocol: 1/2 -> 1 against the measured BTF
    est1 = _half_scale(store, views, paper_nets)
    est1["dong"] = dong_eigentextures(est1["half"], rank=dong_rank, factor=2, alpha=alpha)
    est1["espcn"] = est1[normalisation]
    paper_scores = {m: scores(btf1, est1[m]) for m in METHODS}
    name = Path(btf_path).stem
    figures = _crops(Path(figures_dir), name, btf1, est2, truth2, unit)
    result = {"material": name, "class": (store.attrs.get("material") or {}).get("class"),
            "exact": exact_scores, "paper": paper_scores,
            "paper_normalisation": {norm: scores(btf1, est1[norm]) for norm in compared},
            "regions_exact": {m: {k: float(np.mean([r[k] for r in v])) for k in ("mrmse", "mpsnr", "mre")}
                              for m, v in roi_scores.items()},
            "scale_invariance": {"mre_trained_once": exact_scores["espcn"]["mre"],
                                 "mre_trained_twice": exact_scores["espcn_twice"]["mre"]},
            "training": {k: v[1] for k, v in trained.items()},
            "models": {k: str(Path(models_dir) / f"{name}-{k.replace('_', '-', 1)}.pt") for k in trained},
            "figures": figures, "seconds": round(time.perf_counter() - start, 2)}
    kill_point("chunk-written")                                  # scored, its record not yet written
    write_json(cached, {"key": key, "result": result})
    return {**result, "reused": False}


def _scores_key(store: Any, capture: Any, others: str | None, normalisation: str, alpha: float, dong_rank: int,
                training: dict[str, Any]) -> str:
    """What a test material's scores depend on: its BTF and capture, the others' network, the choices."""
    payload = {"btf": store.content_key, "capture": (capture.group.attrs.get("provenance") or {}).get("config_hash"),
               "others": None if others is None else load_model(others).sha256, "normalisation": normalisation,
               "alpha": alpha, "rank": dong_rank, "training": training, "version": SCORES_VERSION}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]


def _crops(out: Path, name: str, btf1: np.ndarray, est2: dict[str, np.ndarray], truth2: np.ndarray,
           unit: np.ndarray) -> list[dict[str, str]]:
    """Side-by-side crops of one bright, near-frontal row: low resolution, bicubic, Dong, ESPCN, truth."""
    from btfcore.render.tonemap import tonemap
    from tasks.report import save_png

    out.mkdir(parents=True, exist_ok=True)
    n_leds = unit.shape[0]
    row = int(np.argmax(truth2[:n_leds].mean(axis=(1, 2, 3))))       # first view (frontal), brightest light
    H2, W2 = truth2.shape[1:3]
    size = min(64, H2 // 2)
    r0, c0 = (H2 - size) // 2, (W2 - size) // 2
    crop = (slice(r0, r0 + size), slice(c0, c0 + size))
    white = float(np.percentile(truth2[row], 99.5))
    panels = {"low resolution (ingested 1x, nearest)": np.repeat(np.repeat(btf1[row:row + 1], 2, 1), 2, 2),
              **{m: est2[m][row:row + 1] for m in METHODS}}
    images = {label: img[0] * unit[row % n_leds].astype(np.float32) for label, img in panels.items()}
    images["2x ground truth"] = truth2[row]
    figures = []
    for label, rgb in images.items():
        file = out / f"{name}-{label.split(' ')[0]}.png"
        save_png(file, tonemap(rgb[crop], white=white))
        figures.append({"file": f"{out.name}/{file.name}", "caption": f"{name}, row {row}: {label}"})
    return figures


def mean_table(materials: list[dict[str, Any]], protocol: str) -> dict[str, dict[str, float]]:
    """Means over the test materials of each method's scores under ``protocol`` (and of ``espcn_others``,
    the training materials' network, where every material has it)."""
    methods = [*METHODS, *(["espcn_others"] if all("espcn_others" in r[protocol] for r in materials) else [])]
    return {m: {k: float(np.mean([r[protocol][m][k] for r in materials])) for k in ("mrmse", "mpsnr", "mre")}
            for m in methods}


def verdicts(materials: list[dict[str, Any]]) -> dict[str, Any]:
    """The issue's bar: ESPCN beats Dong and bicubic in mPSNR and mRE on every test material, both protocols."""
    failures = []
    for rec in materials:
        for protocol in ("paper", "exact"):
            sc = rec[protocol]
            for other in ("bicubic", "dong"):
                if not (sc["espcn"]["mpsnr"] > sc[other]["mpsnr"] and sc["espcn"]["mre"] < sc[other]["mre"]):
                    failures.append(f"{rec['material']} ({protocol}): ESPCN {sc['espcn']['mpsnr']:.2f} dB, "
                                    f"{sc['espcn']['mre']:.2f} % vs {other} {sc[other]['mpsnr']:.2f} dB, "
                                    f"{sc[other]['mre']:.2f} %")
    once = np.mean([r["scale_invariance"]["mre_trained_once"] for r in materials])
    twice = np.mean([r["scale_invariance"]["mre_trained_twice"] for r in materials])
    return {"espcn_beats_dong_and_bicubic": not failures, "failures": failures,
            "scale_invariance": {"mre_trained_once": float(once), "mre_trained_twice": float(twice),
                                 "relative_difference_percent": float(100 * (twice - once) / twice),
                                 "paper_percent": 3.5}}


def choose(validation: list[dict[str, Any]], default: str) -> tuple[str, float]:
    """The normalisation whose paper-protocol networks have the lower mean mRE on the validation materials
    (``default`` without any), and Dong's alpha of the lowest mean mRE."""
    if not validation:
        return default, 1e-2
    norms = {norm: np.mean([v["espcn_mre"][norm] for v in validation]) for norm in validation[0]["espcn_mre"]}
    alphas = {a: np.mean([v["dong_mre"][a] for v in validation]) for a in validation[0]["dong_mre"]}
    return min(norms, key=norms.get), float(min(alphas, key=alphas.get))


def model_path(out: str | os.PathLike, name: str) -> Path:
    """Where the evaluation keeps its model file ``name``."""
    return Path(out) / "models" / f"{name}.pt"
