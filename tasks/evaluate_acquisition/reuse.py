"""What a rerun of the acquisition evaluation reuses: finished results keyed by a hash of their inputs.

As the other stages do (docs/architecture.md, "Storage contract"), every
finished result of the evaluation is stored with the content key of
everything that determines it, and a rerun reuses it only when that key is
unchanged:

* a held-out material's scores (``scores/<material>.json``), keyed by
  :func:`scores_key`: the evaluation config's numerics, the truth stores'
  ``ingest_hash`` and the model store's basis ``key`` of every material (the
  leave-one-out bases merge the class-mates' bases) and
  :data:`RESULTS_VERSION`;
* a rendered material's reconstruction stores
  (``reconstructions/<material>/<strategy>.zarr``), ``key`` attribute = the
  scores key, reused only when ``complete``;
* a rendered material's renderings and ABRDF images
  (``figures/<material>/figures.json``), keyed by :func:`figures_key` (the
  scores key, the rendering size and whether the environment map exists),
  reused only when every image file is there;
* the demo's model database (``btf build-db``: its leave-one-out table and
  report), keyed by :func:`model_database_key`.

Records are written atomically (written beside, then renamed:
:func:`tasks.report.write_json`), so a killed run leaves either a finished
record or none, and resumes with what is missing.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import zarr

from tasks.evaluate_acquisition.config import EvaluationConfig
from tasks.model import BASES, Material, ModelSettings, discover, stored_key
from tasks.report import reused_text, write_json
from tasks.staging import store_attrs

#: Version of the evaluation's results: bump it when the scores, reconstructions or figures change meaning,
#: so that a rerun recomputes them. 2: every record holds its strategies' noise-free floors. 3: the basis-aware
#: pattern strategies of issue 20 (patterns-quarter, smatrix-quarter). 4: under a non-ideal dome their shots go
#: through its effects too.
RESULTS_VERSION = 4
#: Version of the demo's model-database record (:func:`model_database_key`), apart from the evaluation's
#: results: the model database does not change when they do.
MODEL_DATABASE_VERSION = 1

#: Config fields that only affect what is rendered, kept or added beside the scores, not the scores.
_RENDER_FIELDS = ("render_materials", "render_size", "keep_reconstructions", "adaptive", "adaptive_select",
                  "adaptive_rows", "adaptive_predictor")


def _hash(payload: Any) -> str:
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]


def scores_key(config: EvaluationConfig, model_path: str, materials: Sequence[Material], bases: Sequence[str]
               ) -> str:
    """Content key of the scores and reconstructions: config numerics, truth hashes, basis keys, version.

    Raises
    ------
    ValueError
        When the model store lacks a basis key (an unfinished fit; run it again).
    """
    group = zarr.open_group(model_path, mode="r", zarr_format=3)
    basis_keys = {}
    for m in materials:
        for basis in bases:
            where = f"materials/{m.material_id}/{basis}"
            key = group[where].attrs.get("key") if where in group else None
            if not key:
                raise ValueError(f"{model_path}: basis {where} is missing (an unfinished or other model store); "
                                 "run the fit again (delete the model store to start over)")
            basis_keys[where] = key
    numerics = {k: v for k, v in config.to_json().items() if k not in _RENDER_FIELDS}
    return _hash({"results_version": RESULTS_VERSION, "config": numerics, "bases": basis_keys,
                  "truth": {m.material_id: m.ingest_hash for m in materials}})


def model_database_key(db: str | os.PathLike, model_dir: str | os.PathLike, settings: ModelSettings
                       ) -> str | None:
    """Content key of a finished ``btf build-db`` of ``db`` into ``model_dir`` (the demo's build-db stage).

    A hash of the settings, every material's class and ``ingest_hash`` and the
    ``key`` of every per-material basis in ``model_dir/model.zarr``; None when
    the model store, a basis or ``report.html`` is missing (the stage runs).
    """
    materials = discover(db)
    model_path = Path(model_dir) / "model.zarr"
    if not (Path(model_dir) / "report.html").is_file() or store_attrs(model_path) is None:
        return None
    group = zarr.open_group(str(model_path), mode="r", zarr_format=3)
    keys = {f"{m.material_id}/{b}": stored_key(group, f"materials/{m.material_id}/{b}") for m in materials
            for b in BASES}
    if not all(keys.values()):
        return None
    return _hash({"results_version": MODEL_DATABASE_VERSION, "settings": settings.key(), "bases": keys,
                  "materials": {m.material_id: [m.cls, m.ingest_hash] for m in materials}})


def figures_key(scores: str, render_size: int, env_map: str | None) -> str:
    """Content key of a rendered material's figures: the scores key, the rendering size, the lights."""
    return _hash({"scores": scores, "render_size": render_size, "env_map": env_map is not None})


def read_record(path: str | os.PathLike, key: str) -> dict[str, Any] | None:
    """The record stored at ``path`` under ``key``; None when absent, unreadable or of another key."""
    try:
        stored = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return stored.get("record") if isinstance(stored, dict) and stored.get("key") == key else None


def write_record(path: str | os.PathLike, key: str, record: dict[str, Any]) -> dict[str, Any]:
    """Store ``record`` under ``key`` at ``path``, atomically (write beside, then rename); the record as
    stored (plain JSON types), so that a fresh run returns exactly what a rerun reads back."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_json(path, {"key": key, "record": record})
    return json.loads(Path(path).read_text())["record"]


def figures_present(folder: str | os.PathLike, figures: dict[str, Any]) -> bool:
    """Whether every image file a figures record names is in ``folder``."""
    files = [*figures["abrdf"].values()]
    files += [f for images in figures["renderings"]["images"].values() for f in images.values()]
    return all((Path(folder) / f).is_file() for f in files)


def finished_store(path: str | os.PathLike, key: str) -> bool:
    """Whether the store at ``path`` is complete and was written under ``key``."""
    attrs = store_attrs(path)
    return bool(attrs) and attrs.get("complete") is True and attrs.get("key") == key


def reuse_message(reused: dict[str, list[int]], stage: str = "evaluate acquisition") -> str:
    """One line saying what a stage reused: ``"evaluate acquisition: reused 36 of 36 reconstructions, ..."``.

    ``reused`` is ``{what: [reused, total]}`` (the summary's ``"reused"``).
    """
    return f"{stage}: reused {reused_text(reused)}"
