"""Import camera raw files (DNG and every format LibRaw reads) into a capture store.

Input is a folder of raw files and a manifest (CSV with a header row, or a JSON
list of objects) with one row per file::

    file,turntable,camera,illumination,exposure[,exposure_time][,role]

``exposure_time`` (seconds) may be left out or empty: it is then read from the
file's metadata (LibRaw's shutter speed). ``role`` is ``frame`` (default) or
``dark``; dark rows need ``camera`` and give the calibration dark frames.

Everything is checked before any work starts, and every problem is listed at
once (:class:`RawImportError`): unreadable or truncated files, missing bracket
members, duplicate entries, mismatched sizes, Bayer layouts or levels, missing
or non-increasing exposure times. The dome geometry (LED and camera poses,
turntable angles, homographies) comes from a :class:`Device` calibration whose
region of interest is set to the files' size.
"""

from __future__ import annotations

import csv
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from btfcore.dome import Device
from tasks.compute import run_all
from tasks.stores import CaptureMetadata, CaptureStore, create_capture_store, open_capture_store

MANIFEST_COLUMNS = ("file", "turntable", "camera", "illumination", "exposure")
_INDEX_COLUMNS = MANIFEST_COLUMNS[1:]


@dataclass(frozen=True)
class ManifestRow:
    """One manifest entry; ``line`` is its 1-based line (CSV) or item (JSON) number."""

    line: int
    file: str
    turntable: int
    camera: int
    illumination: int
    exposure: int
    exposure_time: float | None = None
    role: str = "frame"


@dataclass(frozen=True)
class RawFrameInfo:
    """What LibRaw says about one file."""

    shape: tuple[int, int]
    bayer_pattern: str
    black_level_per_channel: tuple[int, int, int, int]
    white_level: int
    exposure_time: float | None


class RawImportError(ValueError):
    """Every problem found in a raw import, one per line, each with what to do."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        super().__init__(f"{len(problems)} problem(s) in the raw import:\n" + "\n".join(f"  - {p}" for p in problems))


def read_manifest(path: str | os.PathLike) -> tuple[list[ManifestRow], list[str]]:
    """Parse a CSV or JSON manifest into rows and the problems of malformed rows."""
    path = Path(path)
    problems: list[str] = []
    try:
        text = path.read_text()
    except OSError as exc:
        return [], [f"{path}: cannot read the manifest ({exc.strerror}); check the path"]
    if path.suffix.lower() == ".json":
        try:
            items = json.loads(text)
        except json.JSONDecodeError as exc:
            return [], [f"{path}: not valid JSON ({exc}); fix the manifest"]
        if not isinstance(items, list):
            return [], [f"{path}: expected a JSON list of objects with keys {', '.join(MANIFEST_COLUMNS)}"]
        records = [(i + 1, item) for i, item in enumerate(items)]
    else:
        reader = csv.DictReader(text.splitlines())
        missing = [c for c in MANIFEST_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            return [], [f"{path}: the header lacks column(s) {', '.join(missing)}; "
                        f"expected {','.join(MANIFEST_COLUMNS)}[,exposure_time][,role]"]
        records = [(i + 2, row) for i, row in enumerate(reader)]
    rows = []
    for line, record in records:
        where = f"{path}:{line}"
        if not isinstance(record, dict) or not record.get("file"):
            problems.append(f"{where}: no 'file' given; every row names one raw file")
            continue
        role = str(record.get("role") or "frame").strip()
        if role not in ("frame", "dark"):
            problems.append(f"{where}: role {role!r} is neither 'frame' nor 'dark'")
            continue
        values: dict[str, Any] = {}
        for column in _INDEX_COLUMNS:
            raw = record.get(column)
            if role == "dark" and column != "camera" and raw in (None, ""):
                values[column] = 0
                continue
            try:
                values[column] = int(raw)
                if values[column] < 0:
                    raise ValueError
            except (TypeError, ValueError):
                problems.append(f"{where}: {column} = {raw!r} is not a non-negative integer")
        time_raw = record.get("exposure_time")
        exposure_time = None
        if time_raw not in (None, ""):
            try:
                exposure_time = float(time_raw)
                if not np.isfinite(exposure_time) or exposure_time <= 0:
                    raise ValueError
            except (TypeError, ValueError):
                problems.append(f"{where}: exposure_time = {time_raw!r} is not a positive number of seconds")
                continue
        if len(values) == len(_INDEX_COLUMNS):
            rows.append(ManifestRow(line, str(record["file"]), exposure_time=exposure_time, role=role, **values))
    return rows, problems


def _pattern_name(raw_pattern: np.ndarray, color_desc: bytes) -> str:
    desc = color_desc.decode()
    return "".join(desc[int(i)] for i in np.asarray(raw_pattern).ravel())


def probe_raw_file(path: str | os.PathLike) -> RawFrameInfo:
    """Read a raw file's layout and levels with LibRaw (the pixel data is decoded too,
    so that truncated files are caught here)."""
    import rawpy

    with rawpy.imread(str(path)) as raw:
        frame = raw.raw_image_visible
        if raw.num_colors != 3 or np.asarray(raw.raw_pattern).shape != (2, 2):
            raise ValueError("not a 2x2 Bayer sensor (LibRaw reports "
                             f"{raw.num_colors} colours, pattern shape {np.asarray(raw.raw_pattern).shape})")
        pattern = _pattern_name(raw.raw_pattern, raw.color_desc)
        shutter = float(raw.other.shutter_speed)
        return RawFrameInfo(
            shape=(int(frame.shape[0]), int(frame.shape[1])),
            bayer_pattern=pattern,
            black_level_per_channel=tuple(int(v) for v in raw.black_level_per_channel),
            white_level=int(raw.white_level),
            exposure_time=shutter if shutter > 0 else None,
        )


def read_raw_frame(path: str | os.PathLike) -> np.ndarray:
    """The visible raw CFA image of a file, ``(rows, cols)`` uint16."""
    import rawpy

    with rawpy.imread(str(path)) as raw:
        return np.array(raw.raw_image_visible, dtype=np.uint16)


@dataclass
class RawImportPlan:
    """A validated raw import: what goes where, ready to run."""

    folder: Path
    shape: tuple[int, int, int, int]                  # (n_turn, n_cam, n_illum, n_exp)
    frame_shape: tuple[int, int]
    bayer_pattern: str
    black_level_per_channel: tuple[int, int, int, int]
    white_level: int
    files: dict[tuple[int, int, int, int], Path]    # (t, c, i, e) -> file
    exposure_time: np.ndarray                        # (n_turn, n_cam, n_illum, n_exp)
    darks: dict[int, list[tuple[float, Path]]] = field(default_factory=dict)


def plan_raw_import(folder: str | os.PathLike, manifest: str | os.PathLike,
                    probe: Callable[[Path], RawFrameInfo] = probe_raw_file) -> RawImportPlan:
    """Check a folder and manifest completely; raise :class:`RawImportError` listing every problem."""
    folder = Path(folder)
    rows, problems = read_manifest(manifest)
    infos: dict[Path, RawFrameInfo] = {}
    seen_keys: dict[tuple, int] = {}
    seen_files: dict[Path, int] = {}
    for row in rows:
        path = folder / row.file
        where = f"{manifest}:{row.line} ({row.file})"
        if path in seen_files:
            problems.append(f"{where}: the same file is also listed on line {seen_files[path]}; list each file once")
        seen_files.setdefault(path, row.line)
        key = ("dark", row.camera, row.line) if row.role == "dark" else (row.turntable, row.camera, row.illumination, row.exposure)
        if key in seen_keys:
            problems.append(f"{where}: duplicate entry for (turntable, camera, illumination, exposure) = "
                            f"{key}, also on line {seen_keys[key]}; remove one")
        seen_keys.setdefault(key, row.line)
        if path in infos:
            continue
        if not path.is_file():
            problems.append(f"{where}: file not found in {folder}; check the name or the folder")
            continue
        try:
            infos[path] = probe(path)
        except Exception as exc:  # LibRaw raises many kinds for corrupt, truncated or foreign files
            problems.append(f"{where}: LibRaw cannot read it ({type(exc).__name__}: {exc}); "
                            "the file is corrupt, truncated or not a camera raw file — re-copy it from the camera")
    frames = [r for r in rows if r.role == "frame"]
    if not frames:
        problems.append(f"{manifest}: no frame rows; nothing to import")
        raise RawImportError(problems)

    # One layout for the whole capture: the most common one is the reference.
    readable = [(r, infos[folder / r.file]) for r in rows if folder / r.file in infos]
    if readable:
        def common(attr):
            values = [getattr(info, attr) for _, info in readable]
            return max(set(values), key=values.count)

        ref = {a: common(a) for a in ("shape", "bayer_pattern", "black_level_per_channel", "white_level")}
        for row, info in readable:
            for attr, value in ref.items():
                if getattr(info, attr) != value:
                    problems.append(f"{manifest}:{row.line} ({row.file}): {attr} is {getattr(info, attr)}, "
                                    f"the other files have {value}; all files of a capture must come from one "
                                    "camera model and mode")
    n_turn, n_cam, n_illum, n_exp = (max(getattr(r, c) for r in frames) + 1 for c in _INDEX_COLUMNS)
    present = {(r.turntable, r.camera, r.illumination, r.exposure): r for r in frames}
    missing = [key for key in np.ndindex(n_turn, n_cam, n_illum, n_exp) if key not in present]
    for key in missing[:20]:
        problems.append(f"{manifest}: bracket member (turntable, camera, illumination, exposure) = {key} is "
                        "missing; add its file or drop the whole bracket")
    if len(missing) > 20:
        problems.append(f"{manifest}: ... {len(missing) - 20} more missing bracket members ({len(missing)} in all)")

    times = np.zeros((n_turn, n_cam, n_illum, n_exp))
    for key, row in present.items():
        info = infos.get(folder / row.file)
        t = row.exposure_time if row.exposure_time is not None else (info.exposure_time if info else None)
        if t is None and info is not None:
            problems.append(f"{manifest}:{row.line} ({row.file}): no exposure_time in the manifest and none in "
                            "the file's metadata; add the exposure_time column")
        times[key] = t or 0.0
    if not missing:
        for t, c, i in np.ndindex(n_turn, n_cam, n_illum):
            bracket = times[t, c, i]
            if (bracket > 0).all() and not (np.diff(bracket) > 0).all():
                problems.append(f"{manifest}: exposure times of bracket (turntable, camera, illumination) = "
                                f"{(t, c, i)} are not increasing with the exposure index: {bracket.tolist()} s; "
                                "number each bracket's exposures from shortest to longest")
    darks: dict[int, list[tuple[float, Path]]] = {}
    for row in rows:
        if row.role != "dark":
            continue
        info = infos.get(folder / row.file)
        t = row.exposure_time if row.exposure_time is not None else (info.exposure_time if info else None)
        if t is None:
            problems.append(f"{manifest}:{row.line} ({row.file}): dark frame without an exposure time")
            continue
        darks.setdefault(row.camera, []).append((t, folder / row.file))
    if darks and sorted(darks) != list(range(n_cam)):
        problems.append(f"{manifest}: dark frames are given for camera(s) {sorted(darks)} but the capture has "
                        f"cameras 0..{n_cam - 1}; give dark frames for every camera or for none")
    if darks and len({tuple(sorted(t for t, _ in v)) for v in darks.values()}) > 1:
        problems.append(f"{manifest}: the cameras' dark frames use different exposure times; use the same set")
    if problems:
        raise RawImportError(problems)
    return RawImportPlan(folder, (n_turn, n_cam, n_illum, n_exp), ref["shape"], ref["bayer_pattern"],
                         ref["black_level_per_channel"], ref["white_level"],
                         {k: folder / r.file for k, r in present.items()}, times,
                         {c: sorted(v) for c, v in darks.items()})


def calibrated_device(device: Device, plan: RawImportPlan) -> Device:
    """The device calibration restricted to the capture's turntable positions, cameras and frame size."""
    n_turn, n_cam, n_illum, _ = plan.shape
    problems = []
    if n_turn > device.n_turn:
        problems.append(f"the manifest uses {n_turn} turntable positions, the calibration of {device.name} has {device.n_turn}")
    if n_cam > device.n_cam:
        problems.append(f"the manifest uses {n_cam} cameras, the calibration of {device.name} has {device.n_cam}")
    if n_illum > device.n_leds:
        problems.append(f"the manifest uses {n_illum} single-LED illuminations, the calibration of {device.name} "
                        f"has {device.n_leds} LEDs (multiplexed imports need their patterns; not supported yet)")
    if problems:
        raise RawImportError([p + "; pass the calibration of the dome that took these files" for p in problems])
    return device.with_overrides(turntable_angle_deg=device.turntable_angle_deg[:n_turn],
                                 camera_indices=list(range(n_cam)), led_indices=list(range(n_illum)),
                                 roi_shape=plan.frame_shape, bayer_pattern=plan.bayer_pattern)


def import_metadata(plan: RawImportPlan, device: Device, provenance: dict[str, Any]) -> CaptureMetadata:
    """Capture-store metadata of a raw import."""
    dark_times = [t for t, _ in plan.darks.get(0, [])] or [float(plan.exposure_time[plan.exposure_time > 0].min())]
    black = plan.black_level_per_channel
    return CaptureMetadata(
        device=device.name, bayer_pattern=plan.bayer_pattern, black_level=int(min(black)),
        white_level=int(plan.white_level), bit_depth=int(max(plan.white_level, 1)).bit_length(),
        sensor={"gain_e_per_dn": None, "read_noise_e": None, "full_well_e": None, "dark_current_e_per_s": None},
        sample_size_m=float(device.sample_size_m), texture_shape=tuple(device.texture_shape),
        illumination=np.eye(plan.shape[2], dtype=np.uint8), led_position=device.led_position,
        camera_K=device.camera_K, camera_R=device.camera_R, camera_t=device.camera_t,
        turntable_angle=device.turntable_angle_deg, homography=device.homographies(),
        dark_exposure_time=np.asarray(dark_times, dtype=np.float64), n_exp=plan.shape[3],
        roi_shape=plan.frame_shape,
        provenance={"source": "ingest", "black_level_per_channel": list(black),
                    "dark_frames": "files" if plan.darks else "synthesised from the black level (no dark rows)",
                    **provenance},
    )


def raw_import_metadata(plan: RawImportPlan, device: Device, provenance: dict[str, Any] | None = None
                        ) -> CaptureMetadata:
    """The capture-store metadata of importing ``plan`` with the dome calibration ``device``, with its
    ``config_hash`` (a fingerprint of the calibration, exposure times and files: a rerun of the same
    import resumes, another one is refused).

    Raises
    ------
    RawImportError
        The manifest uses more turntable positions, cameras or LEDs than the calibration has.
    """
    import hashlib

    device = calibrated_device(device, plan)
    fingerprint = json.dumps({"device": device.to_json(), "times": plan.exposure_time.tolist(),
                              "files": sorted((list(k), str(v)) for k, v in plan.files.items()),
                              "darks": {str(c): [[t, str(p)] for t, p in v] for c, v in plan.darks.items()}},
                             sort_keys=True, default=str)
    provenance = {"config_hash": hashlib.sha256(fingerprint.encode()).hexdigest()[:16], "seed": None,
                  **dict(provenance or {})}
    return import_metadata(plan, device, provenance)


def import_view(store_path: str, meta: CaptureMetadata, plan: RawImportPlan, t: int, c: int) -> tuple[int, int]:
    """Read one view's brackets from their files and write them (owning whole chunks) into the store the
    driver created with ``meta`` (:meth:`CaptureStore.reopen`)."""
    store = CaptureStore.reopen(store_path, meta, "r+")
    _, _, n_illum, n_exp = plan.shape
    frames = np.stack([np.stack([read_raw_frame(plan.files[(t, c, i, e)]) for e in range(n_exp)])
                       for i in range(n_illum)])
    store.write_bracket(t, c, frames, plan.exposure_time[t, c])
    return t, c


def import_raw(plan: RawImportPlan, device: Device, out: str | os.PathLike, client: Any = None, *,
               provenance: dict[str, Any] | None = None, overwrite: bool = False) -> CaptureStore:
    """Write a validated raw import into a capture store, one view per task.

    With a ``distributed.Client`` the views run on the cluster; without, here.
    A rerun resumes with the views not yet written.
    """
    meta = raw_import_metadata(plan, device, provenance)
    store = create_capture_store(out, meta, overwrite=overwrite)
    if plan.darks:
        store.write_dark_frames(np.stack([np.stack([read_raw_frame(p) for _, p in plan.darks[c]])
                                          for c in range(plan.shape[1])]))
    else:
        level = np.full((plan.shape[1], 1, *plan.frame_shape), meta.black_level, dtype=np.uint16)
        store.write_dark_frames(level)
    args = [(str(out), store.meta, plan, t, c) for t, c in store.pending_views()]
    if client is None:
        for a in args:
            import_view(*a)
    else:
        run_all(client, import_view, args)
    store.mark_complete()
    return open_capture_store(out)
