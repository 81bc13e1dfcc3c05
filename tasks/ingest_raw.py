"""Import camera raw files (DNG and every format LibRaw reads) into a capture store.

Input is a folder of raw files and a manifest (CSV with a header row, or a JSON
list of objects) with one row per file::

    file,turntable,camera,illumination,exposure[,exposure_time][,role]

``exposure_time`` is a shutter time as photographers write it (``1/50``, ``0.5``,
``2"``, ``2s``; :func:`parse_shutter_time`); left out or empty, it is read from
the file's metadata (LibRaw's shutter speed). Each bracket is sorted by its
times, so rows and ``exposure`` numbers may come in any order. ``role`` is
``frame`` (default) or ``dark``; dark rows need ``camera`` and give the
calibration dark frames.

Everything is checked before any work starts, and every problem is listed at
once (:class:`RawImportError`), each check running whatever else failed:
unreadable or truncated files, images (PNG, JPEG, TIFF) given instead of raw
files, missing bracket members, duplicate entries, mismatched sizes, Bayer
layouts or levels, missing exposure times or two frames of a bracket at one
time. The white level is the file's (:func:`file_white_level`). The dome geometry (LED and camera poses,
turntable angles, homographies) comes from a :class:`Device` calibration whose
region of interest is set to the files' size.

While a view is written, each bracket is checked to scale with its exposure times
(:func:`bracket_flags`, docs/raw-import.md, "Bracket consistency"): flagged brackets are listed in
the store's ``bracket_warnings`` or, with ``strict_brackets``, fail the import. The manifest check
and the writer also serve :mod:`tasks.ingest_images` (LDR image brackets), which passes its own
file probe, frame reader and camera responses.
"""

from __future__ import annotations

import csv
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from btfcore.capture.hdr import exposure_ratios
from btfcore.dome import BAYER_PATTERNS, Device
from tasks.compute import run_all
from tasks.stores import (
    CaptureMetadata,
    CaptureStore,
    commit_capture,
    create_capture_store,
    reusable_capture,
)
from tasks.stores.common import to_json_attr

MANIFEST_COLUMNS = ("file", "turntable", "camera", "illumination", "exposure")
_INDEX_COLUMNS = MANIFEST_COLUMNS[1:]
_SAME_TIME_RTOL = 1e-6


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
    time_error: bool = False    # the manifest's exposure_time was given but invalid (already reported)


@dataclass(frozen=True)
class RawFrameInfo:
    """What LibRaw says about one file."""

    shape: tuple[int, int]
    bayer_pattern: str
    black_level_per_channel: tuple[int, int, int, int]
    white_level: int
    exposure_time: float | None
    white_level_source: str = "LibRaw white level (file metadata)"


class RawImportError(ValueError):
    """Every problem found in a raw import, one per line, each with what to do."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        super().__init__(f"{len(problems)} problem(s) in the raw import:\n" + "\n".join(f"  - {p}" for p in problems))


_SHUTTER_FORMS = "seconds as 1/50, 1/8000, 0.5, 2\" or 2s"


def parse_shutter_time(value: Any) -> float:
    """A shutter time as photographers write it, in seconds.

    Accepts numbers and the strings ``1/50``, ``1/8000``, ``0.5``, ``2"``, ``2s``, ``2 s``
    (also ``1/50s``). Raises ``ValueError`` saying what is wrong (division by zero, not
    positive, not finite or not a shutter time at all).
    """
    if isinstance(value, bool):
        raise ValueError(f"not a shutter time; write {_SHUTTER_FORMS}")
    if isinstance(value, (int, float)):
        seconds = float(value)
    else:
        text = str(value).strip()
        for suffix in ('"', "\u201d", "sec", "s"):
            if text.lower().endswith(suffix):
                text = text[: -len(suffix)].strip()
                break
        try:
            if "/" in text:
                num, den = (float(part) for part in text.split("/"))
                if den == 0:
                    raise ValueError(f"division by zero; write {_SHUTTER_FORMS}")
                seconds = num / den
            else:
                seconds = float(text)
        except ValueError as exc:
            if "division by zero" in str(exc):
                raise
            raise ValueError(f"not a shutter time; write {_SHUTTER_FORMS}") from None
    if not np.isfinite(seconds):
        raise ValueError(f"not a finite number of seconds; write {_SHUTTER_FORMS}")
    if seconds <= 0:
        raise ValueError(f"a shutter time must be positive, got {seconds:g} s; write {_SHUTTER_FORMS}")
    return seconds


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
        if not isinstance(record, dict):
            problems.append(f"{where}: not an object with keys {', '.join(MANIFEST_COLUMNS)}")
            continue
        has_file = bool(record.get("file"))
        if not has_file:
            problems.append(f"{where}: no 'file' given; every row names one raw file")
        # every check of a row runs, so that one message lists all of the row's problems
        role = str(record.get("role") or "frame").strip()
        role_ok = role in ("frame", "dark")
        if not role_ok:
            problems.append(f"{where}: column 'role' = {role!r} is neither 'frame' nor 'dark'")
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
                values.pop(column, None)
                problems.append(f"{where}: column {column!r} = {raw!r} is not a non-negative integer")
        time_raw = record.get("exposure_time")
        exposure_time, time_error = None, False
        if time_raw not in (None, ""):
            try:
                exposure_time = parse_shutter_time(time_raw)
            except ValueError as exc:
                time_error = True
                problems.append(f"{where}: column 'exposure_time' = {time_raw!r}: {exc}")
        if has_file and role_ok and len(values) == len(_INDEX_COLUMNS):
            rows.append(ManifestRow(line, str(record["file"]), exposure_time=exposure_time, role=role,
                                    time_error=time_error, **values))
    return rows, problems


def _pattern_name(raw_pattern: np.ndarray, color_desc: bytes) -> str:
    desc = color_desc.decode()
    return "".join(desc[int(i)] for i in np.asarray(raw_pattern).ravel())


def file_white_level(raw: Any) -> tuple[int, str]:
    """The level at which an opened rawpy file saturates, and where that value came from.

    LibRaw's ``white_level`` is the file's WhiteLevel (or the format's nominal maximum), but for a
    DNG with a LinearizationTable LibRaw has already mapped every value through the table
    (``raw_image`` is linearised), so no pixel can exceed the table's last entry: a real DNG's
    table ends at 65472 while its white level reads 65535. Order of precedence, lowest wins:

    * per-channel white levels of the file (``camera_white_level_per_channel``), their minimum;
    * LibRaw's ``white_level``;
    * the largest value of LibRaw's decoding curve (``tone_curve``) when it is not the identity
      (a DNG linearisation table or a format's decoding curve).

    Returns
    -------
    level : int
        The white level in raw DN.
    source : str
        ``"per-channel white level (file metadata)"``, ``"LibRaw white level (file metadata)"``,
        ``"linearisation table maximum"`` or ``"default 65535 (the file gives none)"``.
    """
    candidates: list[tuple[int, str]] = []
    per_channel = raw.camera_white_level_per_channel
    if per_channel is not None and any(int(v) > 0 for v in per_channel):
        candidates.append((min(int(v) for v in per_channel if int(v) > 0),
                           "per-channel white level (file metadata)"))
    if int(raw.white_level) > 0:
        candidates.append((int(raw.white_level), "LibRaw white level (file metadata)"))
    curve = np.asarray(raw.tone_curve)
    if curve.size and not np.array_equal(curve, np.arange(curve.size)):
        candidates.append((int(curve.max()), "linearisation table maximum"))
    if not candidates:
        return 65535, "default 65535 (the file gives none)"
    level = min(v for v, _ in candidates)
    return level, next(src for v, src in candidates if v == level)


_IMAGE_SIGNATURES = ((b"\x89PNG\r\n\x1a\n", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"),
                     (b"II*\x00", "a TIFF image"), (b"MM\x00*", "a TIFF image"))


def _tiff_is_dng(head: bytes) -> bool:
    """Whether the first IFD of a TIFF (its first bytes ``head``) carries the DNGVersion tag (50706)."""
    order = "<" if head[:2] == b"II" else ">"
    try:
        offset = int.from_bytes(head[4:8], "little" if order == "<" else "big")
        count = int.from_bytes(head[offset:offset + 2], "little" if order == "<" else "big")
        for k in range(count):
            entry = head[offset + 2 + 12 * k: offset + 4 + 12 * k]
            if len(entry) < 2:
                return False
            if int.from_bytes(entry, "little" if order == "<" else "big") == 50706:
                return True
    except (ValueError, IndexError):
        return False
    return False


def identify_image_file(path: str | os.PathLike) -> str | None:
    """``"a PNG image"``, ``"a JPEG image"`` or ``"a TIFF image"`` when the file starts with that
    format's signature (a TIFF that is a DNG does not count); ``None`` otherwise."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
    except OSError:
        return None
    for signature, kind in _IMAGE_SIGNATURES:
        if head.startswith(signature):
            if kind == "a TIFF image" and _tiff_is_dng(head):
                return None
            return kind
    return None


NOT_RAW_ADVICE = ("the raw path needs camera raw files (DNG or a format LibRaw reads); import brackets of "
                  "8- or 16-bit TIFF, PNG or JPEG images with `btf import-images` (same manifest), which "
                  "calibrates the camera's response")


def probe_raw_file(path: str | os.PathLike) -> RawFrameInfo:
    """Read a raw file's layout and levels with LibRaw (the pixel data is decoded too,
    so that truncated files are caught here). The white level is :func:`file_white_level`'s."""
    import rawpy

    with rawpy.imread(str(path)) as raw:
        frame = raw.raw_image_visible
        if raw.num_colors != 3 or np.asarray(raw.raw_pattern).shape != (2, 2):
            raise ValueError("not a 2x2 Bayer sensor (LibRaw reports "
                             f"{raw.num_colors} colours, pattern shape {np.asarray(raw.raw_pattern).shape})")
        pattern = _pattern_name(raw.raw_pattern, raw.color_desc)
        shutter = float(raw.other.shutter_speed)
        white, source = file_white_level(raw)
        return RawFrameInfo(
            shape=(int(frame.shape[0]), int(frame.shape[1])),
            bayer_pattern=pattern,
            black_level_per_channel=tuple(int(v) for v in raw.black_level_per_channel),
            white_level=white,
            exposure_time=shutter if shutter > 0 else None,
            white_level_source=source,
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
    files: dict[tuple[int, int, int, int], Path]    # (t, c, i, e) -> file, each bracket sorted by time
    exposure_time: np.ndarray                        # (n_turn, n_cam, n_illum, n_exp)
    darks: dict[int, list[tuple[float, Path]]] = field(default_factory=dict)
    white_level_source: str = "LibRaw white level (file metadata)"


def _sort_brackets(manifest: str | os.PathLike, folder: Path,
                   present: dict[tuple[int, int, int, int], ManifestRow], times: np.ndarray,
                   problems: list[str]) -> dict[tuple[int, int, int, int], Path]:
    """Sort every bracket by its exposure times (stable in the manifest's exposure index), in place in
    ``times`` (n_turn, n_cam, n_illum, n_exp); return the files in that order and append a problem for
    every bracket with two frames at one time. Runs on every bracket, complete or not."""
    n_turn, n_cam, n_illum, n_exp = times.shape
    files: dict[tuple[int, int, int, int], Path] = {}
    for t, c, i in np.ndindex(n_turn, n_cam, n_illum):
        members = [(float(times[t, c, i, e]), e, present[(t, c, i, e)]) for e in range(n_exp)
                   if (t, c, i, e) in present]
        ordered = sorted(members, key=lambda m: (m[0], m[1]))
        # times within 1e-6 relative are one time (metadata rationals read as float32 differ by ~1e-8)
        groups: list[list[tuple[float, int, ManifestRow]]] = []
        for member in (m for m in ordered if m[0] > 0):
            if groups and member[0] <= groups[-1][0][0] * (1 + _SAME_TIME_RTOL):
                groups[-1].append(member)
            else:
                groups.append([member])
        for group in (g for g in groups if len(g) > 1):
            problems.append(f"{manifest}: bracket (turntable, camera, illumination) = {(t, c, i)} has "
                            f"{len(group)} frames at the same exposure time {group[0][0]:g} s (lines "
                            f"{', '.join(str(m[2].line) for m in group)}); every frame of a bracket needs its "
                            "own time")
        for e, (seconds, _, row) in enumerate(ordered):
            times[t, c, i, e] = seconds
            files[(t, c, i, e)] = folder / row.file
    return files


def raw_unreadable(where: str, path: Path, exc: Exception) -> str:
    """The problem of a file LibRaw cannot read: an image named as such (and the command that takes it),
    anything else as corrupt, truncated or foreign."""
    kind = identify_image_file(path)
    if kind is not None:
        return f"{where}: {kind}, not a camera raw file (LibRaw cannot read it: {type(exc).__name__}); {NOT_RAW_ADVICE}"
    return (f"{where}: LibRaw cannot read it ({type(exc).__name__}: {exc}); "
            "the file is corrupt, truncated or not a camera raw file — re-copy it from the camera")


def plan_raw_import(folder: str | os.PathLike, manifest: str | os.PathLike,
                    probe: Callable[[Path], RawFrameInfo] = probe_raw_file,
                    unreadable: Callable[[str, Path, Exception], str] = raw_unreadable) -> RawImportPlan:
    """Check a folder and manifest completely; raise :class:`RawImportError` listing every problem.

    ``probe`` reads one file's layout and levels and ``unreadable`` words the problem of a file it
    cannot read: LibRaw's by default, :mod:`tasks.ingest_images`' for LDR images (the one manifest
    check serves both imports)."""
    folder = Path(folder)
    rows, problems = read_manifest(manifest)
    infos: dict[Path, RawFrameInfo] = {}
    seen_keys: dict[tuple, int] = {}
    seen_files: dict[Path, int] = {}
    for row in rows:
        path = folder / row.file
        where = f"{manifest}:{row.line} ({row.file})"
        if Path(row.file).is_absolute() or ".." in Path(row.file).parts:
            problems.append(f"{where}: names a file outside {folder}; a manifest names files inside FOLDER, "
                            "relative to it: copy or move the file into the folder")
            continue
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
            problems.append(unreadable(where, path, exc))
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
        if row.time_error:          # reported already; the file's time is not silently used instead
            t = None
        elif t is None and info is not None:
            problems.append(f"{manifest}:{row.line} ({row.file}): no exposure_time in the manifest and none in "
                            "the file's metadata; add the exposure_time column")
        times[key] = t or 0.0
    files = _sort_brackets(manifest, folder, present, times, problems)
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
                         files, times,
                         {c: sorted(v) for c, v in darks.items()},
                         white_level_source=next(info.white_level_source for _, info in readable
                                                 if info.white_level == ref["white_level"]))


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
                                 roi_shape=plan.frame_shape,
                                 bayer_pattern=plan.bayer_pattern if plan.bayer_pattern in BAYER_PATTERNS
                                 else device.sensor.bayer_pattern)   # an image import's "RGB" is the store's


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
                    "white_level_source": plan.white_level_source,
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


#: A bracket is flagged when two consecutive frames brighten by a factor that differs from the ratio of
#: their exposure times by more than this, either way (docs/raw-import.md, "Bracket consistency").
BRACKET_RATIO_TOLERANCE = 1.25
#: Samples used for the ratios: at least this fraction of the range above black (out of the read noise)
#: and below :data:`_USABLE_HIGH` of it (clear of saturation and a response's flat top).
_USABLE_LOW, _USABLE_HIGH = 0.02, 0.95


def bracket_signal(frames: np.ndarray, black_level: float, white_level: float,
                   response: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One bracket linearised for :func:`btfcore.capture.hdr.exposure_ratios`: ``(signal, usable)``.

    ``frames`` are ``(n_exp, rows, cols)`` raw DN (signal: minus the black level) or, with a camera
    ``response`` ``(n_codes, 3)``, ``(n_exp, rows, cols, 3)`` codes (signal: the response's value).
    Usable: between 2 % and 95 % of the range from black to white."""
    span = float(white_level) - float(black_level)
    usable = (frames >= black_level + _USABLE_LOW * span) & (frames <= black_level + _USABLE_HIGH * span)
    if response is None:
        return frames.astype(np.float32) - np.float32(black_level), usable
    return response[frames.astype(np.intp), np.arange(frames.shape[-1])], usable    # I(z) per channel


def bracket_flags(signal: np.ndarray, usable: np.ndarray, exposure_time: np.ndarray,
                  bracket: tuple[int, int, int]) -> list[dict[str, Any]]:
    """The consecutive frame pairs of one bracket whose brightness ratio is off their exposure-time ratio
    by more than :data:`BRACKET_RATIO_TOLERANCE` (pairs without 64 usable samples are not judged)."""
    measured, expected, n_px = exposure_ratios(signal, usable, exposure_time)
    flags = []
    for j, (m, e, n) in enumerate(zip(measured, expected, n_px)):
        if np.isfinite(m) and abs(np.log(m / e)) > np.log(BRACKET_RATIO_TOLERANCE):
            flags.append({"bracket": [int(v) for v in bracket], "frames": [j, j + 1],
                          "measured_ratio": round(float(m), 4), "expected_ratio": round(float(e), 4),
                          "pixels": int(n)})
    return flags


def bracket_flag_text(flag: dict[str, Any]) -> str:
    """One line saying what is wrong with a flagged bracket and what to check."""
    t, c, i = flag["bracket"]
    j, k = flag["frames"]
    return (f"bracket (turntable, camera, illumination) = ({t}, {c}, {i}): exposures {j} and {k} (sorted by time) "
            f"brighten by {flag['measured_ratio']:.3g}x where their exposure times say "
            f"{flag['expected_ratio']:.3g}x (median over {flag['pixels']} pixels); check the manifest's times "
            "and files for this bracket (one file listed twice, a wrong row) and whether the light flickered")


class BracketConsistencyError(ValueError):
    """Brackets whose frames do not scale with their exposure times, with ``--strict-brackets``."""


def view_bracket_flags(frames: Any, meta: CaptureMetadata, plan: RawImportPlan, t: int, c: int,
                       response: np.ndarray | None = None) -> list[dict[str, Any]]:
    """:func:`bracket_flags` of every bracket of view ``(t, c)``; ``frames[i]`` is illumination ``i``'s
    bracket as read from its files (or, for a view an earlier run wrote, from the store: the same codes)."""
    _, _, n_illum, n_exp = plan.shape
    flags: list[dict[str, Any]] = []
    if n_exp > 1:
        for i in range(n_illum):
            signal, usable = bracket_signal(np.asarray(frames[i]), meta.black_level, meta.white_level, response)
            flags += bracket_flags(signal, usable, plan.exposure_time[t, c, i], (t, c, i))
    return flags


def import_view(store_path: str, meta: CaptureMetadata, plan: RawImportPlan, t: int, c: int,
                read_frame: Callable[[Path], np.ndarray] = read_raw_frame, response: np.ndarray | None = None,
                strict: bool = False) -> tuple[int, int, list[dict[str, Any]]]:
    """Read one view's brackets from their files, check that each scales with its exposure times
    (:func:`bracket_flags`) and write them (owning whole chunks) into the store the driver created with
    ``meta`` (:meth:`CaptureStore.reopen`). ``response`` is the camera's ``(n_codes, 3)`` response of an
    image import. Returns ``(t, c, flags)``; with ``strict`` a flagged view raises
    :class:`BracketConsistencyError` before anything of it is written."""
    store = CaptureStore.reopen(store_path, meta, "r+")
    _, _, n_illum, n_exp = plan.shape
    frames = np.stack([np.stack([read_frame(plan.files[(t, c, i, e)]) for e in range(n_exp)])
                       for i in range(n_illum)])
    flags = view_bracket_flags(frames, meta, plan, t, c, response)
    if strict and flags:
        raise BracketConsistencyError("; ".join(bracket_flag_text(f) for f in flags)
                                      + " (--strict-brackets; leave it out to import with a warning)")
    store.write_bracket(t, c, frames, plan.exposure_time[t, c])
    return t, c, flags


def import_raw(plan: RawImportPlan, device: Device, out: str | os.PathLike, client: Any = None, *,
               provenance: dict[str, Any] | None = None, overwrite: bool = False, strict_brackets: bool = False,
               meta: CaptureMetadata | None = None, read_frame: Callable[[Path], np.ndarray] = read_raw_frame,
               responses: np.ndarray | None = None, response_info: dict[str, Any] | None = None) -> CaptureStore:
    """Write a validated raw import into a capture store, one view per task.

    With a ``distributed.Client`` the views run on the cluster; without, here.
    A rerun resumes with the views not yet written; with ``overwrite`` the new store is built beside
    ``out`` and replaces it once complete (:func:`tasks.stores.capture.create_capture_store`).
    Brackets whose frames do not scale with their exposure times are listed in the store's root
    attribute ``bracket_warnings`` (of every view: those an earlier, killed run wrote are judged again
    from the store; :func:`bracket_flags`), or with ``strict_brackets`` fail the import.
    :mod:`tasks.ingest_images` passes its own ``meta``, ``read_frame`` and the cameras' ``responses``
    ``(n_cam, n_codes, 3)`` (written to the store with ``response_info``).
    """
    meta = raw_import_metadata(plan, device, provenance) if meta is None else meta
    done = reusable_capture(out, meta.provenance["config_hash"], overwrite)
    if done is not None:                  # a finished import of the same files and calibration
        return done
    store = create_capture_store(out, meta, overwrite=overwrite)
    if responses is not None:
        store.write_response(responses, response_info or {})
    if plan.darks:
        store.write_dark_frames(np.stack([np.stack([read_frame(p) for _, p in plan.darks[c]])
                                          for c in range(plan.shape[1])]))
    else:
        level = np.full((plan.shape[1], 1, *plan.frame_shape), meta.black_level, dtype=np.uint16)
        store.write_dark_frames(level)
    pending = store.pending_views()
    args = [(store.path, store.meta, plan, t, c, read_frame, None if responses is None else responses[c],
             strict_brackets) for t, c in pending]
    if client is None:
        results = [import_view(*a) for a in args]
    else:
        results = run_all(client, import_view, args)
    flags = [f for _, _, view_flags in results for f in view_flags]
    # views an earlier, killed run wrote: their flags again from the stored codes, so that a resumed
    # import lists what an uninterrupted one does
    written = store.written == 1
    for t, c in sorted({(int(t), int(c)) for t, c in np.argwhere(written.all(axis=2))} - set(pending)):
        frames = [store.read_bracket(t, c, i)[0] for i in range(plan.shape[2])]
        flags += view_bracket_flags(frames, store.meta, plan, t, c, None if responses is None else responses[c])
    flags.sort(key=lambda f: (f["bracket"], f["frames"]))
    store.group.attrs.update(to_json_attr({"bracket_warnings": flags}))
    return commit_capture(store, out, "import-raw")
