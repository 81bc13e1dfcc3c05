"""An opened capture store (:class:`CaptureStore`): its metadata, shapes and small arrays, reading
brackets and windows of raw frames, and writing whole chunks (brackets, dark frames, ground truth)
with resume markers after the data (docs/capture-store.md; docs/architecture.md, "Storage contract").

Opened by :func:`tasks.stores.capture.open_capture_store` (which validates) or returned by
:func:`tasks.stores.capture.create_capture_store`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import zarr

from tasks.faults import kill_point
from tasks.integrity import (CorruptChunkError, chunk_files_exist, create_array, missing_problem, read_chunk_windows,
                             rerun_hint)
from tasks.stores.capture_schema import (
    META_ARRAY_FIELDS,
    ROTATION_TOL,
    CaptureMetadata,
    CaptureStoreError,
    row_major_lv_index,
    trailing_steps_filled,
)
from tasks.stores.capture_validate import validate_group
from tasks.stores.common import MAX_LISTED, is_url, store_arg, to_json_attr, write_chunk_aligned


class CaptureStore:
    """An opened capture store.

    Use :func:`open_capture_store` or :func:`create_capture_store` rather than
    the constructor, which does not validate.

    Attributes
    ----------
    path : str
        Store path or URL.
    group : zarr.Group
        The root group.
    meta : CaptureMetadata
        Metadata rebuilt from the store.
    raw : zarr.Array
        ``(n_turn, n_cam, n_illum, n_exp, rows, cols)`` uint16 frames.
    dark_frames : zarr.Array
        ``(n_cam, n_dark, rows, cols)`` uint16.
    """

    def __init__(self, path: str | os.PathLike, mode: str = "r", *, group: zarr.Group | None = None,
                 meta: CaptureMetadata | None = None) -> None:
        self.path = str(path) if is_url(path) else os.fspath(path)
        self.mode = mode
        self.group = group if group is not None else zarr.open_group(
            store_arg(path), mode=mode, zarr_format=3)
        self.raw: zarr.Array = self.group["raw"]
        self.dark_frames: zarr.Array = self.group["dark_frames"]
        self.meta = meta if meta is not None else self._read_meta()

    @classmethod
    def reopen(cls, path: str | os.PathLike, meta: CaptureMetadata, mode: str = "r") -> CaptureStore:
        """The store a driver opened (and validated) with :func:`tasks.stores.capture.open_capture_store`
        or created, opened again on a worker with the driver's ``meta``: neither validated nor its
        metadata read again (a view task needs the path and the metadata, not another validation).
        """
        return cls(path, mode, meta=meta)

    def __repr__(self) -> str:
        return (f"CaptureStore({self.path!r}, mode={self.mode!r}, raw={self.raw.shape}, "
                f"complete={self.complete}, pending={len(self.pending_views())} view(s))")

    def _read_meta(self) -> CaptureMetadata:
        a = dict(self.group.attrs)
        arr = {n: self.group[n][...] for n in META_ARRAY_FIELDS}
        return CaptureMetadata(
            device=a.get("device"), bayer_pattern=a.get("bayer_pattern"),
            black_level=a.get("black_level"), white_level=a.get("white_level"),
            bit_depth=a.get("bit_depth"), sensor=dict(a.get("sensor") or {}),
            sample_size_m=a.get("sample_size_m"),
            texture_shape=tuple(a.get("texture_shape") or ()),
            n_exp=int(self.raw.shape[3]), roi_shape=(int(self.raw.shape[4]), int(self.raw.shape[5])),
            provenance=dict(a.get("provenance") or {}), **arr, **self._read_plan(),
        )

    def _read_plan(self) -> dict[str, Any]:
        try:
            plan = self.group["plan"]
        except KeyError:
            return {}
        return {"plan": plan.attrs.get("plan"), "plan_shot": np.asarray(plan["shot"][...])}

    @property
    def is_plan_capture(self) -> bool:
        """Whether the capture executed an acquisition plan (it has a ``plan`` group)."""
        return self.meta.plan_shot is not None

    @property
    def planned(self) -> np.ndarray:
        """``(n_turn, n_cam, n_illum)`` bool: the brackets the capture takes (all without a plan)."""
        if self.meta.plan_shot is None:
            return np.ones((self.n_turn, self.n_cam, self.n_illum), dtype=bool)
        return self.meta.plan_shot >= 0

    # ---- shapes ------------------------------------------------------------
    @property
    def n_turn(self) -> int:
        return int(self.raw.shape[0])

    @property
    def n_cam(self) -> int:
        return int(self.raw.shape[1])

    @property
    def n_illum(self) -> int:
        return int(self.raw.shape[2])

    @property
    def n_exp(self) -> int:
        return int(self.raw.shape[3])

    @property
    def roi_shape(self) -> tuple[int, int]:
        return int(self.raw.shape[4]), int(self.raw.shape[5])

    @property
    def n_leds(self) -> int:
        return int(self.group["led_position"].shape[0])

    @property
    def n_dark(self) -> int:
        return int(self.group["dark_exposure_time"].shape[0])

    @property
    def n_lv(self) -> int:
        return self.n_turn * self.n_cam * self.n_leds

    @property
    def n_views(self) -> int:
        """Turntable positions x cameras: the ingest's tasks (one per view)."""
        return self.n_turn * self.n_cam

    @property
    def texture_shape(self) -> tuple[int, int]:
        h, w = self.meta.texture_shape
        return int(h), int(w)

    # ---- small arrays (read fresh) -------------------------------------
    @property
    def exposure_time(self) -> np.ndarray:
        """``(n_turn, n_cam, n_illum, n_exp)`` float64 seconds (0 where not written)."""
        return self.group["exposure_time"][...]

    @property
    def written(self) -> np.ndarray:
        """``(n_turn, n_cam, n_illum)`` uint8 resume markers."""
        return self.group["written"][...]

    @property
    def illumination(self) -> np.ndarray:
        return self.meta.illumination

    @property
    def led_position(self) -> np.ndarray:
        return self.meta.led_position

    @property
    def camera_K(self) -> np.ndarray:
        return self.meta.camera_K

    @property
    def camera_R(self) -> np.ndarray:
        return self.meta.camera_R

    @property
    def camera_t(self) -> np.ndarray:
        return self.meta.camera_t

    @property
    def turntable_angle(self) -> np.ndarray:
        return self.meta.turntable_angle

    @property
    def homography(self) -> np.ndarray:
        return self.meta.homography

    @property
    def dark_exposure_time(self) -> np.ndarray:
        return self.meta.dark_exposure_time

    @property
    def attrs(self) -> dict:
        return dict(self.group.attrs)

    @property
    def complete(self) -> bool:
        return self.group.attrs.get("complete") is True

    @property
    def has_truth(self) -> bool:
        return "truth" in self.group

    @property
    def response(self) -> tuple[np.ndarray, dict[str, Any]] | None:
        """An ``"RGB"`` capture's camera response and its attributes (``method``, ``source``):
        ``(n_cam, 2**bit_depth, 3)`` float64, relative exposure per code (``btf import-images``); None
        for a raw capture (docs/capture-store.md, "Camera response")."""
        if "response" not in self.group:
            return None
        arr = self.group["response"]
        return np.asarray(arr[...]), dict(arr.attrs)

    def write_response(self, response: np.ndarray, info: Mapping[str, Any]) -> None:
        """Write the camera response of an ``"RGB"`` capture (one chunk) and its attributes ``info``
        (``method``: the merge that goes with it, ``source``: calibrated from which brackets, or a file)."""
        self._writable()
        r = np.asarray(response, dtype=np.float64)
        want = (self.n_cam, 2 ** int(self.meta.bit_depth), 3)
        if r.shape != want or not np.isfinite(r).all() or (r < 0).any():
            raise ValueError(f"{self.path}: response must be finite, >= 0 and of shape {want} (camera, code, "
                             f"channel), got shape {r.shape}")
        arr = create_array(self.group, "response", shape=want, dtype="float64", chunks=want, fill_value=0,
                           dimension_names=["camera", "code", "channel"], compressors=None, overwrite=True)
        arr[...] = r
        arr.attrs.put(to_json_attr(dict(info)))

    @property
    def material(self) -> dict[str, Any] | None:
        """``{"material_id", "class"}`` of a simulated capture (from its ground truth); ``None`` for a
        capture of a real sample, whose class the model database is told separately."""
        if not self.has_truth:
            return None
        material = dict(self.truth.attrs.get("material") or {})
        if not material.get("class_name"):
            return None
        stem = os.path.splitext(os.path.basename(self.path.rstrip("/")))[0]
        return {"material_id": material.get("material_id", stem), "class": material["class_name"]}

    @property
    def truth(self) -> zarr.Group:
        if not self.has_truth:
            raise KeyError(f"{self.path} has no ground truth (created with with_truth=False)")
        return self.group["truth"]

    # ---- reading -------------------------------------------------------------
    def read_bracket(self, t: int, c: int, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Read one exposure bracket.

        Parameters
        ----------
        t, c, i : int
            Turntable, camera and illumination index.

        Returns
        -------
        frames : (n_exp, rows, cols) ndarray of uint16
        exposure_time : (n_exp,) ndarray of float64
            Seconds, increasing.

        Raises
        ------
        CorruptChunkError
            The bracket's chunk fails its checksum or is truncated, or its file is missing although
            ``written[t, c, i]`` marks it written (naming the store, array and chunk).
        """
        if int(self.group["written"][t, c, i]) == 1 and float(self.meta.black_level or 0) > 0:
            chunk = (int(t), int(c), int(i), 0, 0, 0)
            if not chunk_files_exist(self.raw, [chunk])[0]:
                raise missing_problem(self.path, "raw", chunk, "written", chunk[:3],
                                      rerun_hint(self.attrs)).error()
        return self.raw[t, c, i], self.group["exposure_time"][t, c, i]

    def read_raw(self, t: int, c: int, window: tuple[slice, slice], illuminations: Sequence[int] | None = None,
                 out: np.ndarray | None = None) -> np.ndarray:
        """Read a window of the raw brackets of view ``(t, c)``.

        Parameters
        ----------
        t, c : int
            Turntable and camera index.
        window : (slice, slice)
            Rows and columns of the region of interest.
        illuminations : sequence of int, optional
            Illumination indices to read (all when omitted, one read into ``out``).
        out : (n_illum, n_exp, rows, cols) ndarray of uint16, optional
            Buffer to read all illuminations into (reused across views by the ingest).

        Returns
        -------
        (n, n_exp, rows, cols) ndarray of uint16

        Raises
        ------
        CorruptChunkError
            A chunk fails its checksum, is truncated or is missing (naming the store, array and chunk).
        ValueError
            A chunk of a store without checksums does not decode to its shape.
        """
        try:
            if illuminations is None:
                return read_chunk_windows(self.raw, (t, c), (slice(None), window[0], window[1]), out)
            return np.stack([self.raw[t, c, int(i), :, window[0], window[1]] for i in illuminations])
        except (OSError, MemoryError, CorruptChunkError):
            raise                                   # the machine (worth a retry), or already named
        except Exception as exc:  # noqa: BLE001 - a chunk that does not decode to its shape
            raise ValueError(
                f"{self.path}: raw[(t, c)=({t}, {c})] cannot be read ({type(exc).__name__}: {exc}): a chunk file "
                "is corrupt or truncated, so the store is damaged; write the capture again "
                "(btf simulate / btf import-raw)") from exc

    def pending_views(self) -> list[tuple[int, int]]:
        """Views ``(t, c)`` with any bracket not written (or, with truth, no truth yet).

        Returns
        -------
        list of (int, int)
            Row-major order.
        """
        todo = ((self.written != 1) & self.planned).any(axis=2)
        if self.has_truth:
            todo |= self.truth["written"][...] != 1
        return [(int(t), int(c)) for t, c in np.argwhere(todo)]

    # ---- writing -------------------------------------------------------------
    def _writable(self) -> None:
        if self.mode == "r":
            raise PermissionError(
                f"{self.path} is open read-only; use open_capture_store(path, 'r+', "
                "require_complete=False) to write")

    def _view_index(self, t: int, c: int) -> tuple[int, int]:
        if not (0 <= t < self.n_turn and 0 <= c < self.n_cam):
            raise IndexError(f"view (t, c)=({t}, {c}) outside ({self.n_turn}, {self.n_cam}) views")
        return int(t), int(c)

    def _check_frames(self, frames: Any, shape: tuple[int, ...], what: str) -> np.ndarray:
        frames = np.asarray(frames)
        if frames.shape != shape:
            raise ValueError(f"{what}: expected shape {shape}, got {frames.shape}")
        if frames.dtype.kind not in "ui":
            raise ValueError(
                f"{what}: expected integer raw DN (uint16), got {frames.dtype}; do not pass "
                "linearised or float frames as raw")
        bd = int(self.meta.bit_depth)
        if frames.size and (frames.min() < 0 or frames.max() > 2**bd - 1):
            raise ValueError(
                f"{what}: values in [{frames.min()}, {frames.max()}] outside the {bd}-bit range "
                f"[0, {2**bd - 1}]; check bit_depth / the raw decoder's bit shift")
        return frames.astype(np.uint16, copy=False)

    def write_bracket(self, t: int, c: int, frames: np.ndarray, exposure_time: np.ndarray) -> None:
        """Write every illumination's exposure bracket of view ``(t, c)``.

        The view owns whole chunks of ``raw`` (one per illumination),
        ``exposure_time`` and ``written``. The data go first and the marker
        ``written[t, c, :] = 1`` last, so a killed write is redone on resume.
        Writing a view twice is harmless (idempotent).

        Parameters
        ----------
        t, c : int
            Turntable and camera index.
        frames : (n_illum, n_exp, rows, cols) ndarray of uint16
            Raw Bayer frames in DN. In a plan capture only the view's planned
            illuminations (``planned[t, c]``), in order.
        exposure_time : (n_illum, n_exp) ndarray of float
            Seconds, > 0, strictly increasing along the exposure axis (a plan
            capture: the same rows as ``frames``; a shorter bracket ends in 0 s).

        Raises
        ------
        ValueError
            Wrong shape or dtype, values beyond the bit depth, or bad exposure
            times (naming ``(t, c, i)``).
        """
        self._writable()
        t, c = self._view_index(t, c)
        plan = self.meta.plan_shot is not None
        idx = np.flatnonzero(self.planned[t, c])
        shape = (len(idx) if plan else self.n_illum, self.n_exp, *self.roi_shape, *self.raw.shape[6:])
        frames = self._check_frames(frames, shape, f"frames of view (t, c)=({t}, {c})"
                                    + (" (its planned illuminations)" if plan else ""))
        et = np.asarray(exposure_time, dtype=np.float64)
        if et.shape != shape[:2]:
            raise ValueError(f"exposure_time of view ({t}, {c}): expected shape {shape[:2]}, got {et.shape}")
        check = trailing_steps_filled(et) if plan else et
        for k in range(len(et)):
            e, i = check[k], int(idx[k]) if plan else k
            if not (np.isfinite(e).all() and (e > 0).all() and (np.diff(e) > 0).all()):
                raise ValueError(
                    f"exposure_time[(t, c, i)=({t}, {c}, {i})] = {et[k].tolist()}: exposure times must "
                    "be finite, > 0 s and strictly increasing" + (" (then 0 for steps not taken)" if plan else "")
                    + "; check the manifest / EXIF for this bracket")
        if not plan:
            write_chunk_aligned(self.raw, (t, c), frames)
            write_chunk_aligned(self.group["exposure_time"], (t, c), et)
            kill_point("chunk-written")
            write_chunk_aligned(self.group["written"], (t, c), np.ones(self.n_illum, np.uint8))
            return
        full_et = np.zeros((self.n_illum, self.n_exp))
        full_et[idx] = et
        for k, i in enumerate(idx.tolist()):
            write_chunk_aligned(self.raw, (t, c, i), frames[k])        # one chunk per illumination
        write_chunk_aligned(self.group["exposure_time"], (t, c), full_et)
        kill_point("chunk-written")
        write_chunk_aligned(self.group["written"], (t, c), self.planned[t, c].astype(np.uint8))

    def write_dark_frames(self, frames: np.ndarray, *, camera: int | None = None) -> None:
        """Write dark frames (all cameras, or one camera's chunk).

        Parameters
        ----------
        frames : (n_cam, n_dark, rows, cols) or (n_dark, rows, cols) ndarray of uint16
            The latter with ``camera`` given.
        camera : int, optional
            Write only this camera's chunk.
        """
        self._writable()
        rows, cols = self.roi_shape
        if camera is None:
            frames = self._check_frames(frames, (self.n_cam, self.n_dark, rows, cols), "dark frames")
            write_chunk_aligned(self.dark_frames, (slice(None),), frames)
            write_chunk_aligned(self.group["dark_written"], (slice(None),), np.ones(self.n_cam, np.uint8))
        else:
            if not 0 <= camera < self.n_cam:
                raise IndexError(f"camera {camera} outside {self.n_cam} cameras")
            frames = self._check_frames(frames, (self.n_dark, rows, cols), f"dark frames of camera {camera}")
            write_chunk_aligned(self.dark_frames, (camera,), frames)
            write_chunk_aligned(self.group["dark_written"], (camera,), np.ones(1, np.uint8))

    def write_truth_view(self, t: int, c: int, btf: np.ndarray, btf_2x: np.ndarray) -> None:
        """Write the ground-truth BTF rows of view ``(t, c)`` (one chunk each).

        Parameters
        ----------
        t, c : int
            Turntable and camera index.
        btf : (n_leds, h, w, 3) ndarray of float
            Texture-resolution radiance, rows ``lv = (t * n_cam + c) * n_leds + led``.
        btf_2x : (n_leds, 2h, 2w, 3) ndarray of float
            Twice the resolution.
        """
        self._writable()
        truth = self.truth
        t, c = self._view_index(t, c)
        h, w = self.texture_shape
        n = self.n_leds
        for name, a, shp in (("btf", btf, (n, h, w, 3)), ("btf_2x", btf_2x, (n, 2 * h, 2 * w, 3))):
            a = np.asarray(a)
            if a.shape != shp:
                raise ValueError(f"truth {name} of view ({t}, {c}): expected shape {shp}, got {a.shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"truth {name} of view ({t}, {c}) holds NaN/Inf; fix the simulator output")
        lv0 = (t * self.n_cam + c) * n
        write_chunk_aligned(truth["btf"], slice(lv0, lv0 + n), np.asarray(btf, np.float32))
        write_chunk_aligned(truth["btf_2x"], slice(lv0, lv0 + n), np.asarray(btf_2x, np.float32))
        kill_point("chunk-written")
        write_chunk_aligned(truth["written"], (t, c), np.ones((), np.uint8))

    def write_truth_directions(self, light_dir: np.ndarray, view_dir: np.ndarray, lv_index: np.ndarray) -> None:
        """Write the ground-truth light / view directions of every pair.

        Parameters
        ----------
        light_dir, view_dir : (n_lv, 3) ndarray of float
            Unit vectors in the sample frame.
        lv_index : (n_lv, 3) ndarray of int
            ``(turntable, camera, led)`` of each row, row-major.
        """
        self._writable()
        truth = self.truth
        n = self.n_lv
        ld = np.asarray(light_dir, np.float64)
        vd = np.asarray(view_dir, np.float64)
        li = np.asarray(lv_index)
        for name, a in (("light_dir", ld), ("view_dir", vd), ("lv_index", li)):
            if a.shape != (n, 3):
                raise ValueError(f"truth {name}: expected shape ({n}, 3), got {a.shape}")
        for name, a in (("light_dir", ld), ("view_dir", vd)):
            norm = np.linalg.norm(a, axis=1)
            bad = np.flatnonzero(~np.isfinite(norm) | (np.abs(norm - 1) > ROTATION_TOL))
            if len(bad):
                raise ValueError(f"truth {name}: rows {bad[:MAX_LISTED].tolist()} are not finite unit vectors")
        want = row_major_lv_index(self.n_turn, self.n_cam, self.n_leds)
        bad = np.flatnonzero((li != want).any(axis=1))
        if len(bad):
            raise ValueError(
                f"truth lv_index: rows {bad[:MAX_LISTED].tolist()} differ from the row-major "
                "(turntable, camera, led) order")
        write_chunk_aligned(truth["light_dir"], ..., ld)
        write_chunk_aligned(truth["view_dir"], ..., vd)
        write_chunk_aligned(truth["lv_index"], ..., want)

    def write_truth_map(self, name: str, data: np.ndarray) -> zarr.Array:
        """Write a material map ``truth/maps_<name>`` (one chunk, overwritten).

        Parameters
        ----------
        name : str
            Map name, e.g. ``"albedo"``; stored as ``maps_albedo``.
        data : (h, w) or (h, w, k) ndarray
        """
        self._writable()
        data = np.asarray(data)
        if data.dtype.kind == "f" and not np.isfinite(data).all():
            raise ValueError(f"truth map {name!r} holds NaN/Inf")
        key = name if name.startswith("maps_") else f"maps_{name}"
        arr = create_array(self.truth,
            key, shape=data.shape, dtype=data.dtype, chunks=tuple(max(1, s) for s in data.shape),
            fill_value=0, compressors=None, overwrite=True,
            dimension_names=["tex_row", "tex_col", "channel"][: data.ndim] if data.ndim <= 3 else None,
        )
        arr[...] = data
        return arr

    def set_truth_material(self, material: Mapping[str, Any]) -> None:
        """Store the material description as plain-JSON attrs of ``truth/``."""
        self._writable()
        self.truth.attrs.update({"material": to_json_attr(dict(material), "material")})

    def mark_complete(self) -> None:
        """Validate the whole store and set ``complete`` to true.

        Raises
        ------
        CaptureStoreError
            Naming the missing ``(t, c, i)`` brackets (and anything else wrong).
        """
        self._writable()
        problems = validate_group(self.group, require_complete=True, check_flag=False)
        if problems:
            raise CaptureStoreError(self.path, problems)
        self.group.attrs["complete"] = True
