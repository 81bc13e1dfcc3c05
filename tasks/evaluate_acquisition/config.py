"""What the acquisition evaluation depends on: :class:`EvaluationConfig` and the materials of its truth database."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from typing import Any

from btfcore.acquisition.adaptive import MEASURED_ROWS, PREDICTORS, SELECTIONS
from btfcore.dome import DEVICE_NAMES, Device, get_device
from btfcore.simulate.materials import MATERIAL_CLASSES
from btfcore.simulate.nonideal import IDEAL, DomeNonIdeality
from tasks.model import LINEAR_SVD, ModelSettings
from tasks.simulate import MaterialSpec

#: Classes of claim (a) (paper 1 Table 2: the structured classes).
STRUCTURED_CLASSES = ("carpet", "stone", "leather")
#: Marks a truth store written by this package.
TRUTH_KIND = "evaluation-truth"
#: One material of the truth database (the simulator's material record).
TruthSpec = MaterialSpec


@dataclass(frozen=True)
class EvaluationConfig:
    """Everything the acquisition evaluation depends on; its hash keys the truth stores.

    Parameters
    ----------
    device : str
        Dome preset (:data:`btfcore.dome.DEVICE_NAMES`).
    n_turntable : int or None
        Keep the first turntable positions (None: all).
    texture_size : int or None
        Texture side (the truth is rendered at twice this and box-filtered).
    materials_per_class : int
        Materials per class; leave-one-out needs at least 2.
    classes : tuple of str
        Material classes.
    seed : int
        Root seed of materials, samplings and noise.
    band_rows : int
        Texture rows per Dask task (the unit of the chunked reconstruction).
    fill : float
        Brightest value of each image at this fraction of the full well.
    sampling_steps : int
        Steps of the random-swap sampler (paper 1 Alg. 1).
    abrdf_k_fraction : float
        ABRDF bases use at most this fraction of the parabolic-map sample count
        as basis vectors (paper 1: 1024 vectors from 1,369 samples).
    als_iterations : int
        Iterations of the relative-error ALS bases (paper 4).
    als_components : int or None
        Vectors of the per-material ALS bases (None: the thesis' 64).
    render_materials : int
        Materials (the first of each class, in class order) whose
        reconstructions are written and rendered.
    render_size : int
        Side of the renderings, pixels.
    keep_reconstructions : bool
        Keep the rendered materials' reconstruction stores (about 50 MB per
        strategy at the default scale); by default they are removed once
        rendered.
    adaptive : bool
        Also run the adaptive-capture loop on every held-out material (issue 20,
        docs/adaptive-capture.md; about half of the run: 151 of 324 s at the default scale on two
        cores, docs/adaptive-capture.md, "Measured"). Not part of the scores key.
    adaptive_select : {'committee', 'posterior'}
        How the loop chooses the next group (:data:`btfcore.acquisition.adaptive.SELECTIONS`); the
        committee is every other material's ALS basis. Not part of the scores key.
    adaptive_rows : {'fused', 'model'}
        The loop's and the fixed samplings' measured rows: fused with the measurements, or the basis'
        fit only (:data:`btfcore.acquisition.adaptive.MEASURED_ROWS`). Not part of the scores key.
    adaptive_predictor : {'posterior', 'cv', 'probes'}
        The prediction the loop's bar 2 is judged on (:data:`btfcore.acquisition.adaptive.PREDICTORS`;
        ``probes`` also shoots the probe groups, needs ``adaptive_select='committee'``). Not part of the
        scores key.
    non_ideal : DomeNonIdeality
        The dome's non-idealities applied to the simulated measurements
        (:mod:`btfcore.acquisition.nonideal_measurement`); the ideal dome by
        default. Left out of :meth:`to_json` (and so of the scores key) when ideal.
    """

    device: str = "bonn-dome2"
    n_turntable: int | None = 2
    texture_size: int | None = 32
    materials_per_class: int = 2
    classes: tuple[str, ...] = MATERIAL_CLASSES
    seed: int = 0
    band_rows: int = 8
    fill: float = 0.8
    sampling_steps: int = 1500
    abrdf_k_fraction: float = 0.75
    als_iterations: int = 6
    als_components: int | None = 32
    render_materials: int = 1
    render_size: int = 64
    keep_reconstructions: bool = False
    adaptive: bool = True
    adaptive_select: str = "committee"
    adaptive_rows: str = "fused"
    adaptive_predictor: str = "posterior"
    non_ideal: DomeNonIdeality = IDEAL

    def __post_init__(self) -> None:
        problems = []
        if self.device not in DEVICE_NAMES:
            problems.append(f"device {self.device!r} is unknown; choose one of {', '.join(DEVICE_NAMES)}")
        bad = [c for c in self.classes if c not in MATERIAL_CLASSES]
        if bad or not self.classes:
            problems.append(f"classes {bad or '[]'} are unknown; choose from {', '.join(MATERIAL_CLASSES)}")
        if self.materials_per_class < 1:
            problems.append(f"materials_per_class must be >= 1, got {self.materials_per_class}")
        if self.texture_size is not None and self.texture_size < 6:
            problems.append(f"texture_size must be >= 6 (3x3 ABTF patches), got {self.texture_size}")
        if self.n_turntable is not None and self.n_turntable < 1:
            problems.append(f"n_turntable must be >= 1, got {self.n_turntable}")
        if self.band_rows < 1:
            problems.append(f"band_rows must be >= 1, got {self.band_rows}")
        if not 0 <= self.render_materials <= len(self.classes):
            problems.append(f"render_materials must lie in [0, {len(self.classes)}] (one per class), "
                            f"got {self.render_materials}")
        if not 0 < self.abrdf_k_fraction <= 1:
            problems.append(f"abrdf_k_fraction must lie in (0, 1], got {self.abrdf_k_fraction}")
        for name, known in (("adaptive_select", SELECTIONS), ("adaptive_rows", MEASURED_ROWS),
                            ("adaptive_predictor", PREDICTORS)):
            if getattr(self, name) not in known:
                problems.append(f"{name} {getattr(self, name)!r} is unknown; choose one of {', '.join(known)}")
        if self.adaptive_predictor == "probes" and self.adaptive_select != "committee":
            problems.append("adaptive_predictor 'probes' needs adaptive_select 'committee'")
        if not isinstance(self.non_ideal, DomeNonIdeality):
            problems.append(f"non_ideal must be a DomeNonIdeality, got {type(self.non_ideal).__name__}")
        if problems:
            raise ValueError("invalid evaluation config: " + "; ".join(problems))

    def build_device(self) -> Device:
        """The dome with the config's texture size and turntable positions."""
        overrides: dict[str, Any] = {}
        if self.texture_size is not None:
            overrides["texture_shape"] = (self.texture_size, self.texture_size)
        device = get_device(self.device, **overrides)
        if self.n_turntable is not None:
            device = device.with_overrides(turntable_angle_deg=device.turntable_angle_deg[: self.n_turntable])
        return device

    def truth_key(self) -> str:
        """Hash of what determines the truth stores (device, texture, materials, seed)."""
        payload = {"device": self.device, "n_turntable": self.n_turntable, "texture_size": self.texture_size,
                   "classes": list(self.classes), "materials_per_class": self.materials_per_class,
                   "seed": self.seed, "schema": "btf-texture/1.0"}
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["classes"] = list(self.classes)
        if self.non_ideal.is_ideal:
            del d["non_ideal"]            # the configs (and scores keys) of the evaluations before it existed
        return d

    def model_settings(self) -> ModelSettings:
        """Model settings of the leave-one-out bases (the thesis' k capped by the data)."""
        # randomized subspace iteration: with n_lv > texels the Gram route's eigh of an n_lv x n_lv matrix
        # dominates (about 30 s per channel at 4,356 rows on one core)
        # ALS with als_components vectors: its cost grows with their square and dominated the fit
        # the VMV de-noising basis (a plain truncated SVD of linear RGB): paper 4's 64 linear vectors, or the
        # rank of the noise-free truth where that is lower (the wood BTFs have rank ~23 in linear RGB)
        return ModelSettings(k_material={"log_y": None, "u_y": None, "v_y": None, "abtf_log_y": None,
                                         "als": self.als_components, LINEAR_SVD: None},
                             als_iterations=self.als_iterations, seed=self.seed, method="randomized")


def truth_specs(config: EvaluationConfig) -> list[TruthSpec]:
    """Materials of the truth database: ``materials_per_class`` of every class, classes round-robin."""
    return [MaterialSpec.round_robin(index, config.classes, [config.seed, 7331])
            for index in range(config.materials_per_class * len(config.classes))]
