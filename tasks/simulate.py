"""Chunked generation of virtual-dome capture stores (stage 1; docs/simulator-physics.md).

One material is one capture store ``<out>/<material_id>.zarr`` with its ground
truth in ``truth/``. The unit of work is one *view* (turntable position,
camera): it renders the ground-truth textures of all the view's lights at 2x,
forms every illumination pattern's radiance by summing single-LED radiance
(before any sensor noise), projects them into the camera's region of interest,
chooses an exposure bracket as an operator would and exposes the raw Bayer
frames. Each view task owns whole chunks of the store, so views run in any
order on any worker and a killed run resumes with the views still pending.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from collections.abc import Sequence
from typing import Any, Callable

import numpy as np

import btfcore
from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.plan import CapturePlan, validate_plan
from btfcore.simulate.camera import holder_radiance, render_frame, sample_mask
from btfcore.dome import DEVICE_NAMES, Device, get_device
from btfcore.simulate.materials import MATERIAL_CLASSES, MaterialMaps, make_material, white_standard
from btfcore.simulate.render import downsample2, horizon_map, render_view
from btfcore.simulate.nonideal import (
    IDEAL,
    DomeNonIdeality,
    gain_factor,
    hot_pixel_mask,
    led_drift_factors,
    metered_maximum,
    registration_shifts,
    sensor_at_gain,
    shift_images,
)
from btfcore.simulate.sensor import choose_bracket, dark_current_map, dark_frames, expose
from tasks.buffers import heap_arrays
from tasks.stores import (
    CaptureMetadata,
    CaptureStore,
    check_capture_target,
    commit_capture,
    create_capture_store,
    open_capture_store,
    reusable_capture,
)
from tasks.report import write_json
from tasks.stores.common import json_key
from tasks.textures import load_texture_sources

ILLUMINATIONS = ("single", "multiplexed", "both")
#: The flat Lambertian white target (albedo 0.99) a radiometric calibration captures.
WHITE_STANDARD = "white-standard"
#: Seed of the device itself (LED gains, sensor fixed pattern): one physical dome.
DEVICE_SEED = 20151270
#: Exposure times of the calibration dark frames, seconds.
DARK_EXPOSURES = (1e-3, 1e-2, 1e-1, 1.0)
_MAP_NAMES = ("height", "albedo", "roughness", "specular")


@dataclass(frozen=True)
class SimulationConfig:
    """Everything that determines a simulated database; its hash keys resumption.

    Parameters
    ----------
    device : str
        One of :data:`btfcore.dome.DEVICE_NAMES`.
    n_materials : int
        Materials to simulate; classes are assigned round-robin over ``classes``.
    seed : int
        Root seed: material parameters and sensor noise derive from it.
    illumination : {'single', 'multiplexed', 'both'}
        Single-LED patterns, S-matrix patterns, or both stacked (singles first).
    classes : tuple of str
        Material classes to cycle through; ``"white-standard"`` is the flat
        Lambertian target of a radiometric calibration.
    bayer_pattern : str, optional
        Override the device's Bayer layout.
    texture_size : int, optional
        Override the device's texture side (the ground truth is also at 2x).
    n_turntable : int, optional
        Keep only the first positions of the turntable (a pruned run).
    psf_sigma_px : float
        Standard deviation of the cameras' Gaussian point spread function in raw
        pixels; 0 turns the blur off.
    plan : CapturePlan, optional
        Execute this acquisition plan (``btf simulate --plan``): per turntable
        position its shots -- the LEDs on, the cameras, the shutter brackets
        -- instead of ``illumination`` and the automatic brackets. It must be
        a plan for ``device`` (with ``n_turntable`` applied), and is validated
        against it. The ground truth is still the full single-light BTF.
    camera_scale : int
        Cameras with this many times the device's pixels along each axis
        (:meth:`btfcore.dome.Device.with_overrides`, ``pixel_scale``): a larger
        region of interest for the super-resolution evaluation (SR paper §4).
        Left out of :meth:`to_json` (and so of :func:`config_hash`) at 1.
    non_ideal : DomeNonIdeality
        The dome's non-idealities (LED drift, one bracket per multiplexed capture, camera gains,
        registration error, hot pixels; docs/simulator-physics.md, "A dome that is not ideal"). The
        ideal dome by default, left out of :meth:`to_json` (and so of :func:`config_hash`): its stores
        are bit-identical to those written before the option existed.
    """

    device: str = "tiny"
    n_materials: int = 6
    seed: int = 0
    illumination: str = "single"
    classes: tuple[str, ...] = MATERIAL_CLASSES
    bayer_pattern: str | None = None
    texture_size: int | None = None
    n_turntable: int | None = None
    psf_sigma_px: float = 0.0
    plan: CapturePlan | None = None
    camera_scale: int = 1
    non_ideal: DomeNonIdeality = IDEAL

    def __post_init__(self) -> None:
        problems = []
        if self.device not in DEVICE_NAMES:
            problems.append(f"device {self.device!r} is unknown; choose one of {', '.join(DEVICE_NAMES)}")
        if self.n_materials < 1:
            problems.append(f"n_materials must be >= 1, got {self.n_materials}")
        if self.illumination not in ILLUMINATIONS:
            problems.append(f"illumination {self.illumination!r} is unknown; choose one of {', '.join(ILLUMINATIONS)}")
        bad = [c for c in self.classes if c not in (*MATERIAL_CLASSES, WHITE_STANDARD)]
        if bad or not self.classes:
            problems.append(f"material classes {bad or '[]'} are unknown; choose from "
                            f"{', '.join(MATERIAL_CLASSES)} or {WHITE_STANDARD}")
        if self.texture_size is not None and self.texture_size < 4:
            problems.append(f"texture_size must be >= 4, got {self.texture_size}")
        if not 0.0 <= self.psf_sigma_px <= 10.0:
            problems.append(f"psf_sigma_px must lie in [0, 10] raw pixels, got {self.psf_sigma_px}")
        if self.n_turntable is not None and self.n_turntable < 1:
            problems.append(f"n_turntable must be >= 1, got {self.n_turntable}")
        if isinstance(self.camera_scale, bool) or not isinstance(self.camera_scale, int) or self.camera_scale < 1:
            problems.append(f"camera_scale must be an integer >= 1, got {self.camera_scale!r}")
        if not isinstance(self.non_ideal, DomeNonIdeality):
            problems.append(f"non_ideal must be a btfcore.simulate.nonideal.DomeNonIdeality, got "
                            f"{type(self.non_ideal).__name__}")
        if problems:
            raise ValueError("invalid simulation config: " + "; ".join(problems))
        if self.plan is not None:
            if not isinstance(self.plan, CapturePlan):
                raise ValueError(f"plan must be a btfcore.acquisition.plan.CapturePlan, got {type(self.plan).__name__}")
            if self.plan.device != self.device:
                raise ValueError(f"the plan was made for device {self.plan.device!r}, the simulation is of "
                                 f"{self.device!r}; pass --device {self.plan.device} or plan for {self.device}")
            device = self.build_device()
            validate_plan(self.plan, device)                    # names the shot and the LED/camera/position
            shape, want = (self.plan.n_turn, self.plan.n_cam, self.plan.n_leds), (device.n_turn, device.n_cam,
                                                                                   device.n_leds)
            if shape != want:
                raise ValueError(f"the plan is for {shape[0]} turntable positions x {shape[1]} cameras x {shape[2]} "
                                 f"LEDs, the simulated device has {want[0]} x {want[1]} x {want[2]}"
                                 f"{' (--turntable ' + str(self.n_turntable) + ')' if self.n_turntable else ''}; "
                                 "plan for the device as simulated")
            from tasks.measurement import plan_layout
            plan_layout(self.plan)                              # one bracket per (t, c, pattern)

    def build_device(self) -> Device:
        """The :class:`Device` this config simulates, with its overrides applied."""
        overrides: dict[str, Any] = {}
        if self.texture_size is not None:
            overrides["texture_shape"] = (self.texture_size, self.texture_size)
        if self.psf_sigma_px:
            overrides["sensor"] = {"psf_sigma_px": float(self.psf_sigma_px)}
        device = get_device(self.device, bayer_pattern=self.bayer_pattern, **overrides)
        if self.n_turntable is not None:
            device = device.with_overrides(turntable_angle_deg=device.turntable_angle_deg[: self.n_turntable])
        return device.with_overrides(pixel_scale=self.camera_scale) if self.camera_scale != 1 else device

    def to_json(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "plan"}
        if self.camera_scale == 1:
            del d["camera_scale"]            # the configs (and hashes) of the stores written before it existed
        if self.non_ideal.is_ideal:
            del d["non_ideal"]               # likewise
        else:
            d["non_ideal"] = self.non_ideal.to_json()
        d["classes"] = list(self.classes)
        if self.plan is not None:                             # the whole plan is in each store's plan group
            from tasks.stores.measurement import plan_summary
            d["plan"] = plan_summary(self.plan.to_dict())
        return d


@dataclass(frozen=True)
class MaterialSpec:
    """One material of a simulated database."""

    index: int
    material_id: str
    class_name: str
    seed: int

    @classmethod
    def round_robin(cls, index: int, classes: Sequence[str], seed_words: Sequence[int]) -> MaterialSpec:
        """Material ``index`` of a database whose classes take turns; its seed from ``[*seed_words, index]``."""
        class_name = classes[index % len(classes)]
        seed = int(np.random.SeedSequence([*seed_words, index]).generate_state(1)[0])
        return cls(index, f"{index:03d}-{class_name}", class_name, seed)


def material_plan(config: SimulationConfig) -> list[MaterialSpec]:
    """The materials of a database, classes round-robin, seeds derived from the root seed."""
    return [MaterialSpec.round_robin(index, config.classes, [config.seed]) for index in range(config.n_materials)]


def illumination_patterns(n_leds: int, illumination: str) -> np.ndarray:
    """Binary patterns ``(n_illum, n_leds)``: identity, S-matrix rows, or both stacked."""
    singles = np.eye(n_leds, dtype=np.uint8)
    if illumination == "single":
        return singles
    multiplexed = multiplexing_patterns(n_leds)
    if illumination == "multiplexed":
        return multiplexed
    return np.concatenate([singles, multiplexed])


def code_version() -> str:
    """Package version plus the git commit when run from a checkout."""
    import subprocess

    root = Path(__file__).resolve().parents[1]
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True,
                             text=True, timeout=5, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        rev = ""
    return f"{btfcore.__version__}+g{rev}" if rev else btfcore.__version__


def config_hash(config: SimulationConfig, spec: MaterialSpec) -> str:
    """SHA-256 of everything that determines one material's store."""
    payload = {"config": config.to_json(), "material": asdict(spec), "schema": "btf-capture/1.0"}
    return json_key(payload)


def capture_metadata(config: SimulationConfig, spec: MaterialSpec, device: Device) -> CaptureMetadata:
    """The store metadata of one simulated material."""
    sensor = device.sensor
    plan: dict[str, Any] = {}
    illumination, n_exp = None, int(sensor.n_exposures)
    if config.plan is not None:
        from tasks.measurement import plan_layout
        illumination, shot, times = plan_layout(config.plan)
        plan = {"plan": config.plan.to_dict(), "plan_shot": shot}
        n_exp = int(times.shape[-1])
    return CaptureMetadata(
        device=device.name,
        bayer_pattern=sensor.bayer_pattern,
        black_level=int(sensor.black_level),
        white_level=int(sensor.white_level),
        bit_depth=int(sensor.bit_depth),
        sensor={
            "gain_e_per_dn": float(sensor.gain_e_per_dn),
            "read_noise_e": float(sensor.read_noise_e),
            "full_well_e": float(sensor.full_well_e),
            "dark_current_e_per_s": float(sensor.dark_current_e_per_s),
        },
        sample_size_m=float(device.sample_size_m),
        texture_shape=tuple(int(v) for v in device.texture_shape),
        illumination=(illumination_patterns(device.n_leds, config.illumination) if illumination is None
                      else illumination),
        led_position=device.led_position,
        camera_K=device.camera_K,
        camera_R=device.camera_R,
        camera_t=device.camera_t,
        turntable_angle=device.turntable_angle_deg,
        homography=device.homographies(),
        dark_exposure_time=np.asarray(DARK_EXPOSURES, dtype=np.float64),
        n_exp=n_exp,
        roi_shape=tuple(int(v) for v in device.roi_shape),
        provenance={
            "code_version": code_version(),
            "config_hash": config_hash(config, spec),
            "seed": int(spec.seed),
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "source": "simulator",
            "simulation": config.to_json(),
            "material_id": spec.material_id,
            "material_class": spec.class_name,
        },
        **plan,
    )


def prepare_material(store_path: str, config: SimulationConfig, spec: MaterialSpec) -> str:
    """Draw the material, write its maps, horizon map, directions and dark frames.

    Idempotent: everything written is a deterministic function of the config.
    """
    device = config.build_device()
    store = open_capture_store(store_path, mode="r+", require_complete=False)
    h, w = device.texture_shape
    if spec.class_name == WHITE_STANDARD:
        maps = white_standard((2 * h, 2 * w))
    else:
        maps = make_material(spec.class_name, spec.seed, (2 * h, 2 * w), load_texture_sources())
    for name in _MAP_NAMES:
        store.write_truth_map(name, np.ascontiguousarray(getattr(maps, name), dtype=np.float32))
    store.write_truth_map("horizon", horizon_map(maps.height))
    store.set_truth_material({"class_name": maps.class_name, "f0": [float(v) for v in maps.f0],
                              "params": maps.params, "seed": spec.seed, "material_id": spec.material_id})
    store.write_truth_directions(*device.lv_directions())
    darks = np.stack([
        dark_frames(device.sensor, camera_dark_map(device, c), np.asarray(DARK_EXPOSURES),
                    device.roi_shape, np.random.default_rng([config.seed, spec.index, c, 1 << 20]))
        for c in range(device.n_cam)
    ])
    store.write_dark_frames(darks)
    return store_path


def load_material_maps(store: CaptureStore) -> tuple[MaterialMaps, np.ndarray]:
    """Read the material maps and horizon map back from a store's ``truth/``."""
    truth = store.truth
    attrs = truth.attrs["material"]
    maps = MaterialMaps(
        class_name=attrs["class_name"],
        f0=np.asarray(attrs["f0"], dtype=np.float32),
        params=attrs["params"],
        **{name: truth[f"maps_{name}"][...] for name in _MAP_NAMES},
    )
    return maps, truth["maps_horizon"][...]


def pattern_frames(device: Device, weights: np.ndarray, truth_2x: np.ndarray, turntable: int,
                   camera: int) -> tuple[np.ndarray, np.ndarray]:
    """The radiance reaching one camera's region of interest under each illumination pattern, before
    the sensor (the frames :func:`simulate_view` exposes and the floors of :mod:`tasks.floors` re-expose).

    Parameters
    ----------
    weights : (n_illum, n_leds) ndarray
        Each pattern's LEDs (binary drive).
    truth_2x : (n_leds, 2h, 2w, 3) ndarray
        The view's single-LED ground truth at twice the texture resolution.

    Returns
    -------
    frames : (n_illum, rows, cols, 3) ndarray of float32
        Radiance per raw pixel, BTF units times the LEDs' RGB gains (holder around the sample).
    mask : (rows, cols) ndarray of bool
        Pixels on the sample.
    """
    gain = device.led_rgb_gain.astype(np.float32)                           # (n_leds, 3)
    texture = np.einsum("il,lc,lhwc->ihwc", weights, gain, truth_2x, optimize=True)
    background = weights @ (gain * holder_radiance(device.light_dirs(turntable))[:, None])   # (n_illum, 3)
    frames = render_frame(texture, background, device.homography(turntable, camera),
                          device.roi_shape, device.sample_size_m)
    return frames, sample_mask(device, turntable, camera)


def roi_truth(device: Device, truth_2x: np.ndarray, t: int, c: int, factor: int = 1) -> np.ndarray:
    """The noise-free single-LED radiance of view ``(t, c)``'s region of interest, at ``factor`` times
    the camera's pixels: the truth the super-resolved regions are compared with (SR paper §4).

    Rendered like :func:`pattern_frames` (the holder's radiance around the sample,
    :func:`btfcore.simulate.camera.render_frame`), but one frame per LED, without the LEDs' RGB
    gains, the PSF or the sensor, by ``device.with_overrides(pixel_scale=factor)``.

    Parameters
    ----------
    device : Device
        The dome of the capture (:meth:`SimulationConfig.build_device`).
    truth_2x : (n_leds, 2h, 2w, 3) ndarray
        The view's stored 2x ground truth (``truth/btf_2x`` rows of view ``(t, c)``), BTF units.
    t, c : int
        Turntable position and camera.
    factor : int
        Pixels of the rendered region per camera pixel along each axis; exact only where the 2x
        texture has at least one texel per rendered pixel (docs/simulator-physics.md).

    Returns
    -------
    roi : (n_leds, rows * factor, cols * factor, 3) ndarray of float32
        BTF units (a white Lambertian sample of albedo ``a`` reads ``a cos(theta_i) / pi``).
    """
    truth_2x = np.asarray(truth_2x, dtype=np.float32)
    if truth_2x.ndim != 4 or truth_2x.shape[0] != device.n_leds or truth_2x.shape[-1] != 3:
        raise ValueError(f"truth_2x must be ({device.n_leds}, 2h, 2w, 3), one view's LEDs, got {truth_2x.shape}")
    camera = device.with_overrides(pixel_scale=factor)
    background = np.repeat(holder_radiance(device.light_dirs(t))[:, None], 3, axis=1)       # (n_leds, 3)
    return render_frame(truth_2x, background, camera.homography(t, c), camera.roi_shape, camera.sample_size_m)


def camera_dark_map(device: Device, camera: int) -> np.ndarray:
    """Camera ``camera``'s dark-current map (e-/s per raw pixel), the same for every run of the dome."""
    rng = np.random.default_rng([DEVICE_SEED, camera])
    return dark_current_map(device.sensor, device.roi_shape, rng)


@heap_arrays()
def simulate_view(store_path: str, config: SimulationConfig, spec: MaterialSpec, turntable: int,
                  camera: int, _prepared: Any = None) -> tuple[int, int]:
    """Render, project and expose every illumination of one view; write its chunks."""
    device = config.build_device()
    store = open_capture_store(store_path, mode="r+", require_complete=False)
    maps, horizon = load_material_maps(store)
    truth_2x = render_view(maps, device.view_dir(turntable, camera), device.light_dirs(turntable), horizon)
    store.write_truth_view(turntable, camera, downsample2(truth_2x), truth_2x)

    # Light superposes: each pattern's radiance is the weighted sum of its LEDs'
    # radiance, formed before the sensor adds noise (the linearity multiplexing rests on: VMV paper §3.2).
    weights = store.meta.illumination.astype(np.float32)                    # (n_illum, n_leds)
    planned_times = None
    if config.plan is not None:                 # a plan: only its patterns at this view, its brackets
        from tasks.measurement import plan_layout
        _, shot, plan_times = plan_layout(config.plan)
        taken = np.flatnonzero(shot[turntable, camera] >= 0)
        if not taken.size:
            return turntable, camera                                        # the plan takes nothing here
        weights, planned_times = weights[taken], plan_times[turntable, camera, taken]
    rng = np.random.default_rng([config.seed, spec.index, turntable, camera])
    if not config.non_ideal.is_ideal:
        shots = (np.arange(weights.shape[0]) if config.plan is None else taken)
        raw, times = _expose_nonideal(device, config, spec, weights, shots, store.meta.illumination.shape[0],
                                      truth_2x, turntable, camera, planned_times, rng)
        store.write_bracket(turntable, camera, raw, times)
        return turntable, camera
    frames, mask = pattern_frames(device, weights, truth_2x, turntable, camera)
    if planned_times is None:
        times = choose_bracket(frames, device.sensor, mask=mask)            # (n_illum, n_exp)
    else:
        times = planned_times                   # shorter brackets end in 0 s: those frames stay 0
    raw = expose(frames[:, None], np.where(times > 0, times, 1e-6), device.sensor,
                 camera_dark_map(device, camera), rng)
    raw[times == 0] = 0
    store.write_bracket(turntable, camera, raw, times)
    return turntable, camera


def _expose_nonideal(device: Device, config: SimulationConfig, spec: MaterialSpec, weights: np.ndarray,
                     shots: np.ndarray, n_shots: int, truth_2x: np.ndarray, turntable: int, camera: int,
                     planned_times: np.ndarray | None, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Raw brackets ``(n, n_exp, rows, cols)`` and their exposure times ``(n, n_exp)`` of one view under a
    dome that is not ideal (docs/simulator-physics.md, "A dome that is not ideal").

    ``weights`` ``(n, n_leds)`` are the view's patterns, ``shots`` their indices among the capture's
    ``n_shots`` illuminations. Each LED of shot ``i`` at this turntable position shines ``led_drift_factors``
    times its intensity (the draw, seeded by the position, is the same for every camera); each
    pattern's radiance is shifted by its own registration offset; single-light patterns are read at
    ``single_gain_db``, multiplexed ones at ``multiplex_gain_db`` (a frame's recorded exposure time is
    its shutter time times :func:`~btfcore.simulate.nonideal.gain_factor`, the scale the HDR merge
    divides by); with ``multiplex_single_exposure`` the multiplexed patterns share the bracket of the
    pattern metered on (:func:`~btfcore.simulate.nonideal.metered_maximum`); hot pixels read the white
    level in every frame (not in the dark frames).
    """
    dome = config.non_ideal
    drift = led_drift_factors(dome.led_drift, np.random.default_rng([config.seed, spec.index, turntable, 1 << 21]),
                              (n_shots, device.n_leds))[shots]
    frames, mask = pattern_frames(device, (weights * drift).astype(np.float32), truth_2x, turntable, camera)
    shifts = registration_shifts(dome.registration_sd_px,
                                 np.random.default_rng([config.seed, spec.index, turntable, camera, 1 << 22]),
                                 n_shots)[shots]
    frames = shift_images(frames, shifts)
    multiplexed = weights.sum(axis=1) > 1
    raw = np.empty((frames.shape[0], int(device.sensor.n_exposures) if planned_times is None
                    else planned_times.shape[1], *device.roi_shape), dtype=np.uint16)
    times = np.zeros(raw.shape[:2])
    dark = camera_dark_map(device, camera)
    for kind, gain_db in ((False, dome.single_gain_db), (True, dome.multiplex_gain_db)):
        idx = np.flatnonzero(multiplexed == kind)
        if not idx.size:
            continue
        sensor = sensor_at_gain(device.sensor, gain_db)
        if planned_times is None:
            shutter = choose_bracket(frames[idx], sensor, mask=mask)
            if kind and dome.multiplex_single_exposure:                  # one bracket, metered on the median
                first = shutter[:, 0]
                metered = 1.0 / metered_maximum(1.0 / first)[0]          # t_1 = h F / r_max: median of r_max
                shutter = np.broadcast_to(shutter[int(np.argmin(np.abs(first - metered)))], shutter.shape)
        else:
            shutter = planned_times[idx] / gain_factor(gain_db)          # the plan's times are recorded ones
        raw[idx] = expose(frames[idx][:, None], np.where(shutter > 0, shutter, 1e-6), sensor, dark, rng)
        raw[idx] = np.where((shutter == 0)[..., None, None], 0, raw[idx])
        times[idx] = (shutter * gain_factor(gain_db) if planned_times is None    # the scale the HDR merge
                      else planned_times[idx])                                 # divides by
    hot = hot_pixel_mask(dome.hot_pixel_fraction, np.random.default_rng([DEVICE_SEED, camera, 5]), device.roi_shape)
    if hot.any():
        raw[:, :, hot] = np.where(times[..., None] > 0, device.sensor.white_level, 0)
    return raw, times


@dataclass
class SimulationResult:
    """What a simulation run produced and how long it took."""

    out_dir: str
    stores: list[str]
    materials: list[dict[str, Any]]
    views_done: int
    views_skipped: int
    seconds: float


def estimated_bytes(config: SimulationConfig) -> int:
    """Bytes the database of ``config`` takes on disk (uncompressed arrays)."""
    device = config.build_device()
    h, w = device.texture_shape
    rows, cols = device.roi_shape
    if config.plan is not None:
        raw = sum(s.n_exposures * len(s.cameras) for s in config.plan.shots) * rows * cols * 2
    else:
        n_illum = illumination_patterns(device.n_leds, config.illumination).shape[0]
        raw = device.n_turn * device.n_cam * n_illum * device.sensor.n_exposures * rows * cols * 2
    truth = device.n_lv * h * w * 3 * 4 * (1 + 4)          # btf and btf_2x, float32
    return config.n_materials * (raw + truth)


def check_disk_space(config: SimulationConfig, out_dir: Path) -> None:
    """Refuse to start a simulation that cannot fit on the output's filesystem."""
    import shutil

    need = estimated_bytes(config)
    probe = out_dir
    while not probe.exists():
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if need > free:
        raise ValueError(
            f"{out_dir}: the {config.device} database of {config.n_materials} material(s) needs about "
            f"{need / 1e9:.1f} GB but only {free / 1e9:.1f} GB are free there; choose another --out, fewer "
            "--materials, a pruned --turntable N or a smaller --texture-size"
        )


def check_outputs(config: SimulationConfig, out_dir: str | Path, overwrite: bool = False) -> None:
    """Everything ``btf simulate`` refuses about its output, checked before any work (the CLI calls it
    before a cluster starts): the disk space of a new database, and every store at ``out_dir`` that
    is neither this run's (finished or resumable) nor to be replaced with ``overwrite``.

    Raises
    ------
    ValueError
        Not enough free space.
    FileExistsError
        A store of another configuration, or something that is no capture store (names ``--overwrite``).
    """
    out_dir = Path(out_dir)
    if not (out_dir / "database.json").exists():
        check_disk_space(config, out_dir)
    if overwrite:
        return
    device = config.build_device()
    for spec in material_plan(config):
        check_capture_target(out_dir / f"{spec.material_id}.zarr", capture_metadata(config, spec, device),
                             with_truth=True)


def simulate_database(config: SimulationConfig, out_dir: str | Path, client: Any, *,
                      overwrite: bool = False,
                      progress: Callable[[int, int], None] | None = None) -> SimulationResult:
    """Simulate every material of ``config`` into ``out_dir`` on a Dask cluster.

    Finished stores are left alone (they are reported as skipped); unfinished
    ones resume with their pending views only.

    Parameters
    ----------
    client : distributed.Client
        Where the per-view work runs.
    progress : callable, optional
        Called as ``progress(done, total)`` after each finished view.
    """
    from tasks.compute import wait_all

    start = time.perf_counter()
    out_dir = Path(out_dir)
    check_outputs(config, out_dir, overwrite)
    out_dir.mkdir(parents=True, exist_ok=True)
    device = config.build_device()
    futures, stores, skipped, records = [], [], 0, []
    for spec in material_plan(config):
        path = out_dir / f"{spec.material_id}.zarr"
        store = reusable_capture(path, config_hash(config, spec), overwrite)
        if store is None:        # new, resumed, or (overwrite) built beside the old store until complete
            store = create_capture_store(path, capture_metadata(config, spec, device), with_truth=True,
                                         overwrite=overwrite)
            pending = store.pending_views()
            if pending:
                prepared = client.submit(prepare_material, store.path, config, spec, pure=False,
                                         key=f"prepare-{spec.material_id}-{time.time_ns()}")
            for t, c in pending:
                futures.append(client.submit(simulate_view, store.path, config, spec, t, c, prepared,
                                             pure=False))
            skipped += device.n_turn * device.n_cam - len(pending)
        else:
            skipped += device.n_turn * device.n_cam
        stores.append((path, store.path))
        records.append({"material_id": spec.material_id, "class": spec.class_name, "seed": spec.seed,
                        "store": str(path)})
    total = len(futures)
    wait_all(futures, progress)  # re-raises a worker's error here, naming the view
    for path, written in stores:
        commit_capture(open_capture_store(written, mode="r+", require_complete=False), path, "simulate")
    index = {"schema": "btf-database", "schema_version": "1.0", "simulation": config.to_json(),
             "materials": records}
    write_json(out_dir / "database.json", index)
    return SimulationResult(str(out_dir), [str(path) for path, _ in stores], records, total, skipped,
                            time.perf_counter() - start)
