"""Super-resolution of a BTF store (SR paper): model files, training data from stored regions, and
``btf superres apply`` chunked over views on the Dask cluster.

* **Model files** (:func:`save_model`, :func:`load_model`): a ``torch.save`` dict of the
  network's state dict, its :class:`btfcore.superres.espcn.EspcnConfig`, the training provenance
  and a SHA-256 over every tensor, read back with ``torch.load(weights_only=True)`` (no pickled
  code runs); a file of another format, architecture or scale, or one whose tensors changed, is
  refused with the file and the fix.
* **Training data** (:func:`training_images`): 118 of each store's rows (SR paper §5.1),
  their regions of interest (``btf ingest --keep-roi``) area-down-sampled once (``"exact"``
  protocol: learn 1/2 -> 1, apply 1 -> 2) or twice (``"paper"``: learn 1/4 -> 1/2, apply 1/2 -> 1),
  one image per colour channel.
* **Application** (:func:`superres_apply`): one task per view reads the view's regions, up-samples
  them (:func:`btfcore.superres.regions.upsample_regions`) and rectifies them at twice the texture
  size (:func:`btfcore.superres.regions.rectify_regions`), then writes the view's rows of a new
  ``btf-texture`` store and its marker; resumable and staged like ``btf resample``.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from btfcore.superres.regions import UPSAMPLE_METHODS, rectify_regions, scale_homography, upsample_regions
from btfcore.superres.scaling import area_downsample
from tasks.compute import run_all
from tasks.faults import kill_point
from tasks.staging import commit_staged, staged_target, staging_path, store_attrs, trash_path, write_file
from tasks.stores.btf import (
    LV_ORDER,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    BtfStore,
    band_rows,
    create_btf_store,
    open_btf_store,
)

__all__ = ["MODEL_FORMAT", "PROTOCOLS", "LoadedModel", "apply_view", "check_apply", "load_model", "save_model",
           "one_torch_thread", "superres_apply", "superres_hash", "torch_device", "train_model", "training_images", "view_rows",
           "with_regions"]

#: ``format`` of a model file.
MODEL_FORMAT = "btf-espcn"
MODEL_FORMAT_VERSION = 1
#: Down-sampling steps from the measured region to the training target: ``exact`` learns 1/2 -> 1
#: (applied 1 -> 2 against the simulator's 2x truth), ``paper`` 1/4 -> 1/2 (SR paper §5.1, applied 1/2 -> 1).
PROTOCOLS: dict[str, int] = {"exact": 0, "paper": 1}
#: Images per material the SR paper trained on (§5.1: 118 per material, 2,124 in all; its "about 5 %" of a
#: 26,136-row BTF would be 1,307, so the count is what we follow, docs/super-resolution.md).
PAPER_IMAGES = 118
SUPERRES_FACTOR = 2


def one_torch_thread() -> None:
    """One torch thread in a Dask task: a worker runs as many tasks as it has threads (docs/architecture.md,
    "Pitfalls": oversubscribed BLAS threads)."""
    import torch

    torch.set_num_threads(1)


def torch_device() -> str:
    """``"cuda"`` when a GPU is present, else ``"cpu"`` (the results agree within float tolerance)."""
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


# --------------------------------------------------------------------------- model files


def _digest(state: dict[str, Any]) -> str:
    """SHA-256 over the names, dtypes, shapes and bytes of every tensor of a state dict."""
    sha = hashlib.sha256()
    for name in sorted(state):
        t = state[name].detach().cpu().contiguous()
        sha.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        sha.update(t.numpy().tobytes() if t.dtype.is_floating_point or t.numel() else b"")
    return sha.hexdigest()


def save_model(path: str | os.PathLike, state: dict[str, Any], config: Any, provenance: dict[str, Any]) -> Path:
    """Write a trained network: its state dict, configuration and provenance, atomically.

    Parameters
    ----------
    state : dict of str to torch.Tensor
        ``Espcn.state_dict()`` (batch-norm running statistics included).
    config : btfcore.superres.espcn.EspcnConfig
    provenance : dict
        Plain JSON: the training stores, rows, settings, history, seconds.
    """
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {name: t.detach().cpu().clone() for name, t in state.items()}
    payload = {"format": MODEL_FORMAT, "format_version": MODEL_FORMAT_VERSION,
               "config": json.dumps(config.to_json()), "provenance": json.dumps(provenance, default=str),
               "state_dict": state, "sha256": _digest(state)}
    write_file(path, lambda tmp: torch.save(payload, tmp))   # never a half-written model at ``path``
    return path


@dataclass
class LoadedModel:
    """A model file read back: the network in eval mode, its configuration and provenance."""

    model: Any
    config: Any
    provenance: dict[str, Any]
    sha256: str
    path: str


def load_model(path: str | os.PathLike, *, device: str = "cpu", scale: int | None = SUPERRES_FACTOR) -> LoadedModel:
    """Read a model file written by :func:`save_model` (``torch.load(weights_only=True)``).

    Raises
    ------
    FileNotFoundError
        Nothing at ``path``.
    ValueError
        Not a model file of this format (or unreadable), tensors that do not match the stored
        checksum (tampered or corrupted), a state dict of another architecture than its
        configuration, or a network of another ``scale``: each naming the file and the fix.
    """
    import pickle
    import zipfile

    import torch

    from btfcore.superres.espcn import EspcnConfig, load_espcn

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such model file; train one with `btf superres train`")
    fix = "train it again with `btf superres train` (or give the model file it wrote)"
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, zipfile.BadZipFile, RuntimeError, EOFError, OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable model file ({type(exc).__name__}: {str(exc)[:160]}); {fix}") from None
    if not isinstance(payload, dict) or payload.get("format") != MODEL_FORMAT:
        raise ValueError(f"{path}: not a {MODEL_FORMAT} model file (format "
                         f"{payload.get('format') if isinstance(payload, dict) else type(payload).__name__!r}); {fix}")
    if payload.get("format_version") != MODEL_FORMAT_VERSION:
        raise ValueError(f"{path}: model file version {payload.get('format_version')!r}, this code reads "
                         f"{MODEL_FORMAT_VERSION}; {fix}")
    state = payload.get("state_dict")
    if not isinstance(state, dict) or _digest(state) != payload.get("sha256"):
        raise ValueError(f"{path}: the weights do not match the file's SHA-256 (the file was changed or is "
                         f"corrupted); {fix}")
    try:
        config = EspcnConfig.from_json(json.loads(payload["config"]))
        model = load_espcn(state, config)
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"{path}: the weights are not those of the network its configuration describes "
                         f"({str(exc).splitlines()[0][:200]}); {fix}") from None
    if scale is not None and int(config.scale) != int(scale):
        raise ValueError(f"{path}: a network of scale {config.scale}; this pipeline up-samples by {scale}: "
                         f"train a model with scale {scale}")
    model.eval().to(device)
    return LoadedModel(model, config, json.loads(payload.get("provenance") or "{}"), payload["sha256"], str(path))


_loaded: dict[tuple[str, float, str], LoadedModel] = {}


def _cached_model(path: str, device: str) -> LoadedModel:
    """One :func:`load_model` per worker process and file version (views of a stage share it)."""
    key = (str(path), os.stat(path).st_mtime, device)
    if key not in _loaded:
        _loaded.clear()
        _loaded[key] = load_model(path, device=device)
    return _loaded[key]


# --------------------------------------------------------------------------- stores with regions


def with_regions(path: str | os.PathLike, hint: str = "") -> BtfStore:
    """Open a finished BTF store that holds regions of interest (``btf ingest --keep-roi``), or say why not."""
    store = open_btf_store(path, produced_by="`btf ingest --keep-roi`",
                           ingested_only="super-resolution works on the regions of an ingested store")
    if store.roi is None or "homography" not in store.group:
        raise ValueError(f"{path}: the store holds no regions of interest (arrays roi, homography); ingest the "
                         f"capture again with `btf ingest CAPTURE --out BTF --keep-roi`{hint}")
    return store


def view_rows(store: BtfStore, t: int, c: int) -> slice:
    """The rows of view ``(t, c)`` of an ingested store (rows over (turntable, camera, light))."""
    _, n_cam, n_leds = store.attrs["turntable_cameras_leds"]
    first = (t * n_cam + c) * n_leds
    return slice(first, first + n_leds)


def _finite(regions: np.ndarray, where: str) -> np.ndarray:
    bad = ~np.isfinite(regions)
    if bad.any():
        index = tuple(int(v) for v in np.argwhere(bad)[0])
        raise ValueError(f"{where}: {int(bad.sum())} NaN or Inf values in roi, first at index {index}; "
                         "ingest the capture again (`btf ingest --keep-roi --overwrite`) or leave the store out")
    return regions


def training_images(stores: list[BtfStore], *, protocol: str = "exact", fraction: float | None = None,
                    seed: int = 0) -> tuple[np.ndarray, np.ndarray, list[dict[str, Any]]]:
    """Low- and high-resolution training images from the regions of interest of some stores.

    :data:`PAPER_IMAGES` of each store's rows (all of a smaller store), or ``fraction`` of them (at least
    one), are drawn with ``seed``; the high-resolution
    image is the region down-sampled :data:`PROTOCOLS` ``[protocol]`` times by 2x2 block means
    (:func:`btfcore.superres.scaling.area_downsample`), the low-resolution one that image down-sampled
    once more; each colour channel is one image (SR paper §4: one input channel).

    Returns
    -------
    low : (m, h, w) ndarray of float32
    high : (m, 2h, 2w) ndarray of float32
    drawn : list of dict
        Per store: its path and the rows drawn (the training provenance).
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"protocol {protocol!r} is unknown; choose one of {', '.join(PROTOCOLS)}")
    if not stores:
        raise ValueError("no training stores given; give at least one BTF store ingested with --keep-roi")
    rng = np.random.default_rng(seed)
    lows, highs, drawn = [], [], []
    for store in stores:
        n_lv = store.n_lv
        n = min(n_lv, PAPER_IMAGES) if fraction is None else max(1, int(round(fraction * n_lv)))
        rows = np.sort(rng.choice(n_lv, size=n, replace=False))
        high = _finite(np.asarray(store.roi.oindex[rows, :, :, :], dtype=np.float32), str(store.path))
        for _ in range(PROTOCOLS[protocol]):
            high = area_downsample(high, 2)
        low = area_downsample(high, 2)
        high = high[:, :2 * low.shape[1], :2 * low.shape[2]]
        lows.append(np.moveaxis(low, -1, 1).reshape(-1, *low.shape[1:3]))
        highs.append(np.moveaxis(high, -1, 1).reshape(-1, *high.shape[1:3]))
        drawn.append({"store": str(store.path), "rows": rows.tolist()})
    shapes = {a.shape[1:] for a in lows}
    if len(shapes) > 1:
        raise ValueError(f"the training stores' regions differ in size ({sorted(shapes)} after down-sampling); "
                         "train on stores of one dome and camera")
    return np.concatenate(lows), np.concatenate(highs), drawn


def train_model(btf_paths: list[str | os.PathLike], model_path: str | os.PathLike, *, protocol: str = "exact",
                fraction: float | None = None, config: Any = None, settings: Any = None,
                progress: Callable[[int, dict], None] | None = None) -> dict[str, Any]:
    """``btf superres train``: patches from the stores' regions, the ESPCN trained on them, the model file.

    Training is one small sequential job (seconds to minutes); it runs
    in the calling process with torch's threads, where the flow runs. Returns the summary that is also
    the model file's provenance.
    """
    from btfcore.superres.espcn import EspcnConfig
    from btfcore.superres.training import TrainingSettings, patch_pairs, train_espcn

    config = EspcnConfig() if config is None else config
    settings = TrainingSettings() if settings is None else settings
    stores = [with_regions(p) for p in btf_paths]
    key = hashlib.sha256(json.dumps({"stores": [s.content_key for s in stores], "protocol": protocol,
                                     "fraction": fraction, "config": config.to_json(),
                                     "settings": repr(settings)}, sort_keys=True).encode()).hexdigest()[:16]
    if Path(model_path).exists():
        try:
            previous = load_model(model_path, scale=None)
        except ValueError:
            previous = None                                  # not a model of ours: trained again over it
        if previous is not None and previous.provenance.get("key") == key:
            return {"model": str(Path(model_path).resolve()), **previous.provenance, "reused": True}
    low, high, drawn = training_images(stores, protocol=protocol, fraction=fraction, seed=settings.seed)
    low_patches, high_patches = patch_pairs(low, high, scale=config.scale, normalisation=config.normalisation)
    if len(low_patches) == 0:
        raise ValueError(f"no 17 x 17 training patch fits in the regions ({low.shape[1]} x {low.shape[2]} pixels "
                         f"after down-sampling for the {protocol!r} protocol); use the 'exact' protocol or "
                         "captures with larger regions (`btf simulate --camera-scale 2`)")
    usable = np.ptp(low_patches.reshape(len(low_patches), -1), axis=1) > 0      # a constant patch teaches nothing
    if usable.sum() < 2:
        raise ValueError(f"{', '.join(str(p) for p in btf_paths)}: {int(usable.sum())} of {len(low_patches)} training "
                         "patches hold any image structure (the drawn regions are constant: dark or empty); train on "
                         "captures of a lit sample, or draw more rows with --fraction")
    low_patches, high_patches = low_patches[usable], high_patches[usable]
    start = time.perf_counter()
    result = train_espcn(low_patches, high_patches, config, settings, progress=progress)
    provenance = {"key": key, "protocol": protocol, "fraction": fraction, "stores": drawn,
                  "patches": int(len(low_patches)), **result.provenance(),
                  "seconds": round(time.perf_counter() - start, 2)}
    save_model(model_path, result.state, config, provenance)

    return {"model": str(Path(model_path).resolve()), **provenance, "reused": False}


# --------------------------------------------------------------------------- btf superres apply


def superres_hash(source: BtfStore, model_sha256: str | None, method: str) -> str:
    """What a super-resolved store depends on: the source's content, the method and the model's weights."""
    payload = {"source": source.content_key, "method": method, "model": model_sha256, "factor": SUPERRES_FACTOR,
               "schema": f"{SCHEMA_NAME}/{SCHEMA_VERSION}"}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]


def check_apply(btf_path: str | os.PathLike, model_path: str | os.PathLike | None, out_path: str | os.PathLike, *,
                method: str = "espcn", overwrite: bool = False) -> tuple[BtfStore, LoadedModel | None, str, Path, bool]:
    """Everything ``btf superres apply`` refuses, before any work: the source store, the model, ``--out``.

    Returns the opened source, the model (``None`` for bicubic), the content key, the store to write
    and whether it is the staging store of a replacement (:func:`tasks.staging.staged_target`).
    """
    if method not in UPSAMPLE_METHODS:
        raise ValueError(f"--method {method!r} is unknown; choose one of {', '.join(UPSAMPLE_METHODS)}")
    source = with_regions(btf_path)
    loaded = None
    if method == "espcn":
        if model_path is None:
            raise ValueError("--method espcn needs --model MODEL.pt (from `btf superres train`)")
        loaded = load_model(model_path)
    out = Path(out_path)
    src = Path(btf_path).resolve()
    if src in {p.resolve() for p in (out, staging_path(out), trash_path(out))}:
        raise ValueError(f"--out {out_path} is (or stages into) the source store; choose another --out")
    key = superres_hash(source, None if loaded is None else loaded.sha256, method)

    def refusal(attrs: dict[str, Any]) -> FileExistsError:
        what = (f"holds a super-resolved store of another source, model or method (superres_hash "
                f"{attrs.get('superres_hash')!r}, this run {key!r})" if attrs.get("superres_hash") else
                "holds something that is not a super-resolved BTF store" if attrs else "exists and is no store")
        return FileExistsError(f"{out_path} {what}; choose another --out or pass --overwrite (the new store is "
                               f"then built in {staging_path(out)} and replaces it only once complete)")
    return (source, loaded, key, *staged_target(out, "superres_hash", key, overwrite, refusal))


def apply_view(source_path: str, model_path: str | None, out_path: str, method: str, t: int, c: int) -> tuple[int, int]:
    """Up-sample view ``(t, c)``'s regions, rectify them at twice the texture size, write the view's rows."""
    one_torch_thread()
    source, out = BtfStore(source_path), BtfStore(out_path, "r+")
    rows = view_rows(source, t, c)
    regions = _finite(np.asarray(source.roi[rows], dtype=np.float32), f"{source_path}, view {(t, c)}")
    device = torch_device()
    model = None if model_path is None else _cached_model(model_path, device).model
    up = upsample_regions(regions, method=method, model=model, factor=SUPERRES_FACTOR, device=device)
    h, w = out.texture_shape
    H = scale_homography(source.homography[t, c], SUPERRES_FACTOR)
    out.group["btf"][rows] = rectify_regions(up, H, (h, w), float(source.attrs["sample_size_m"]))
    kill_point("chunk-written")
    out.group["written"][t, c] = 1                                                 # marker after the data
    return t, c


def _create_output(target: Path, source_path: str | os.PathLike, source: BtfStore, loaded: LoadedModel | None,
                   method: str, key: str) -> BtfStore:
    h, w = source.texture_shape
    n_turn, n_cam, n_leds = source.attrs["turntable_cameras_leds"]
    model = None if loaded is None else {"path": loaded.path, "sha256": loaded.sha256,
                                         "config": loaded.config.to_json()}
    return create_btf_store(target, {
        "units": source.units, "lv_order": LV_ORDER, "superres_hash": key, "source": str(source_path),
        "superres": {"method": method, "factor": SUPERRES_FACTOR, "model": model,
                     "source_ingest_hash": source.content_key},
        "turntable_cameras_leds": [n_turn, n_cam, n_leds], "material": source.attrs.get("material"),
        "sample_size_m": source.attrs["sample_size_m"],
    }, light_dir=source.light_dir, view_dir=source.view_dir, lv_index=source.lv_index,
        texture_shape=(SUPERRES_FACTOR * h, SUPERRES_FACTOR * w), rows_per_chunk=n_leds,
        band=band_rows(n_leds, SUPERRES_FACTOR * h, SUPERRES_FACTOR * w), written_shape=(n_turn, n_cam))


def superres_apply(btf_path: str | os.PathLike, model_path: str | os.PathLike | None, out_path: str | os.PathLike,
                   client: Any, *, method: str = "espcn", overwrite: bool = False,
                   progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Super-resolve a BTF store with regions of interest into a ``btf-texture`` store at twice the texture size.

    One Dask task per view; a rerun with the same source, model and method writes only the views not
    yet marked; ``overwrite`` builds the new store beside the old one and swaps it in when complete.
    """
    start = time.perf_counter()
    source, loaded, key, target, staged = check_apply(btf_path, model_path, out_path, method=method,
                                                      overwrite=overwrite)
    attrs = store_attrs(target) or {}
    store = BtfStore(target, "r+") if attrs.get("superres_hash") == key else \
        _create_output(target, btf_path, source, loaded, method, key)
    pending = [] if store.complete else [(t, c) for t, c in np.ndindex(store.written.shape)
                                         if not store.written[t, c]]
    model_file = None if loaded is None else loaded.path
    run_all(client, apply_view, [(str(btf_path), model_file, str(target), method, t, c) for t, c in pending],
            progress)
    store.mark_complete("views")
    if staged:
        commit_staged(out_path, "superres apply")
    h, w = store.texture_shape
    return {"out": str(Path(out_path).resolve()), "method": method, "texture_shape": [h, w],
            "views_processed": len(pending), "views_skipped": int(store.written.size) - len(pending),
            "staged": staged, "device": torch_device(), "seconds": round(time.perf_counter() - start, 3)}
