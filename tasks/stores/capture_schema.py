"""The ``btf-capture`` 1.0 schema: names, units, the array table and :class:`CaptureMetadata`
(docs/capture-store.md).

What a capture store holds and how it is laid out, in one place: :mod:`tasks.stores.capture_validate`
checks a store against it and :mod:`tasks.stores.capture` creates, opens and writes stores by it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from tasks.stores.common import StoreProblemsError

SCHEMA_NAME = "btf-capture"
SCHEMA_VERSION = "1.0"
from btfcore.dome import BAYER_PATTERNS  # noqa: E402  (defined once, with the sensor spec)
LV_ORDER = ["turntable", "camera", "light"]
UNITS = {"exposure_time": "s", "positions": "m", "turntable_angle": "deg"}
SOURCES = ("simulator", "ingest")
SENSOR_KEYS = ("gain_e_per_dn", "read_noise_e", "full_well_e", "dark_current_e_per_s")

#: Tolerance for orthonormality of rotations and unit length of directions.
ROTATION_TOL = 1e-6
#: Largest accepted condition number of a homography.
HOMOGRAPHY_MAX_COND = 1e12


class CaptureStoreError(StoreProblemsError):
    """A capture store (or the metadata for one) violates the schema.

    Parameters
    ----------
    path : str
        Store path or URL.
    problems : list of Problem
        Every problem found, not only the first.
    """

    kind = "capture store"
    schema = f"{SCHEMA_NAME} {SCHEMA_VERSION}"


# --------------------------------------------------------------------------
# Metadata
# --------------------------------------------------------------------------


@dataclass(eq=False)
class CaptureMetadata:
    """Everything about a capture except the frames.

    Parameters
    ----------
    device : str
        Device name.
    bayer_pattern : {"RGGB", "BGGR", "GRBG", "GBRG"}
        The 2x2 top-left block of the raw frame, read row-major.
    black_level, white_level, bit_depth : int
        Sensor black level and saturation level in DN, ADC bit depth.
    sensor : dict
        ``gain_e_per_dn``, ``read_noise_e``, ``full_well_e``,
        ``dark_current_e_per_s``: floats, or None where unknown.
    sample_size_m : float
        Side of the square material sample in metres.
    texture_shape : (2,) tuple of int
        ``(h, w)`` of the rectified texture.
    illumination : (n_illum, n_leds) ndarray of {0, 1}
        LED on/off pattern of each illumination.
    led_position : (n_leds, 3) ndarray
        LED positions in metres, world frame (z up, sample centre at origin).
    camera_K : (n_cam, 3, 3) ndarray
        Intrinsics for the raw frame's pixel grid (the ROI).
    camera_R : (n_cam, 3, 3) ndarray
        World -> camera rotations.
    camera_t : (n_cam, 3) ndarray
        World -> camera translations in metres.
    turntable_angle : (n_turn,) ndarray
        Turntable angles in degrees.
    homography : (n_turn, n_cam, 3, 3) ndarray
        Sample-plane metric coordinates ``(x, y, 1)`` (metres, sample frame)
        to raw-frame pixels ``(col, row, 1)``.
    dark_exposure_time : (n_dark,) ndarray
        Exposure times of the dark frames in seconds, increasing.
    n_exp : int
        Exposures per bracket.
    roi_shape : (2,) tuple of int
        ``(rows, cols)`` of a raw frame.
    provenance : dict
        ``code_version``, ``config_hash``, ``seed``, ``created``, ``source``
        plus free extra keys (plain JSON).
    plan : dict, optional
        A capture executed from an acquisition plan: the plan's plain-JSON
        form (:meth:`btfcore.acquisition.plan.CapturePlan.to_dict`), kept in the store's
        ``plan`` group.
    plan_shot : (n_turn, n_cam, n_illum) ndarray of int, optional
        With ``plan``: the plan's shot index of each bracket ``(t, c, i)``,
        ``-1`` where the plan takes no such bracket (it is never written).
        Brackets of a plan capture may be shorter than ``n_exp``: their
        trailing exposure times are 0 (steps not taken).
    """

    device: str
    bayer_pattern: str
    black_level: int
    white_level: int
    bit_depth: int
    sensor: dict
    sample_size_m: float
    texture_shape: tuple[int, int]
    illumination: np.ndarray
    led_position: np.ndarray
    camera_K: np.ndarray
    camera_R: np.ndarray
    camera_t: np.ndarray
    turntable_angle: np.ndarray
    homography: np.ndarray
    dark_exposure_time: np.ndarray
    n_exp: int
    roi_shape: tuple[int, int]
    provenance: dict
    plan: dict | None = None
    plan_shot: np.ndarray | None = None

    @property
    def n_turn(self) -> int:
        return int(np.shape(self.turntable_angle)[0])

    @property
    def n_cam(self) -> int:
        return int(np.shape(self.camera_K)[0])

    @property
    def n_illum(self) -> int:
        return int(np.shape(self.illumination)[0])

    @property
    def n_leds(self) -> int:
        return int(np.shape(self.led_position)[0])

    @property
    def n_dark(self) -> int:
        return int(np.shape(self.dark_exposure_time)[0])

    @property
    def n_lv(self) -> int:
        return self.n_turn * self.n_cam * self.n_leds

    @property
    def raw_shape(self) -> tuple[int, ...]:
        """``(n_turn, n_cam, n_illum, n_exp, rows, cols)``, and ``3`` channels last for an ``"RGB"`` capture."""
        rgb = (3,) if self.bayer_pattern == "RGB" else ()
        return (self.n_turn, self.n_cam, self.n_illum, int(self.n_exp), *map(int, self.roi_shape), *rgb)

    @property
    def config_hash(self) -> str | None:
        return (self.provenance or {}).get("config_hash")


# Scalar attribute fields of CaptureMetadata and array fields (store name == field name).
META_ATTR_FIELDS = (
    "device", "bayer_pattern", "black_level", "white_level", "bit_depth",
    "sensor", "sample_size_m", "texture_shape",
)
META_ARRAY_FIELDS = (
    "illumination", "led_position", "camera_K", "camera_R", "camera_t",
    "turntable_angle", "homography", "dark_exposure_time",
)


# --------------------------------------------------------------------------
# Array specification
# --------------------------------------------------------------------------


# name -> (dtype, ((dimension_name, size_key), ...), chunk rule)
# chunk rule: None -> one chunk for the whole array; otherwise a tuple where an
# int is a fixed chunk length and a str is the size key (full axis).
ARRAYS: dict[str, tuple[str, tuple[tuple[str, str], ...], tuple | None]] = {
    "raw": (
        "uint16",
        (("turntable", "turntable"), ("camera", "camera"), ("illumination", "illumination"),
         ("exposure", "exposure"), ("row", "row"), ("col", "col")),
        (1, 1, 1, "exposure", "row", "col"),
    ),
    "exposure_time": (
        "float64",
        (("turntable", "turntable"), ("camera", "camera"), ("illumination", "illumination"),
         ("exposure", "exposure")),
        (1, 1, "illumination", "exposure"),
    ),
    "written": (
        "uint8",
        (("turntable", "turntable"), ("camera", "camera"), ("illumination", "illumination")),
        (1, 1, "illumination"),
    ),
    "turntable_angle": ("float64", (("turntable", "turntable"),), None),
    "homography": (
        "float64",
        (("turntable", "turntable"), ("camera", "camera"), ("i", "3"), ("j", "3")),
        None,
    ),
    "camera_K": ("float64", (("camera", "camera"), ("i", "3"), ("j", "3")), None),
    "camera_R": ("float64", (("camera", "camera"), ("i", "3"), ("j", "3")), None),
    "camera_t": ("float64", (("camera", "camera"), ("xyz", "3")), None),
    "illumination": ("uint8", (("illumination", "illumination"), ("led", "led")), None),
    "led_position": ("float64", (("led", "led"), ("xyz", "3")), None),
    "dark_frames": (
        "uint16",
        (("camera", "camera"), ("dark", "dark"), ("row", "row"), ("col", "col")),
        (1, "dark", "row", "col"),
    ),
    "dark_exposure_time": ("float64", (("dark", "dark"),), None),
    "dark_written": ("uint8", (("camera", "camera"),), (1,)),
}
TRUTH_ARRAYS: dict[str, tuple[str, tuple[tuple[str, str], ...], tuple | None]] = {
    "truth/btf": (
        "float32",
        (("lv", "lv"), ("tex_row", "tex_row"), ("tex_col", "tex_col"), ("channel", "3")),
        ("led", "tex_row", "tex_col", "3"),
    ),
    "truth/btf_2x": (
        "float32",
        (("lv", "lv"), ("tex2_row", "tex2_row"), ("tex2_col", "tex2_col"), ("channel", "3")),
        ("led", "tex2_row", "tex2_col", "3"),
    ),
    "truth/light_dir": ("float64", (("lv", "lv"), ("xyz", "3")), None),
    "truth/view_dir": ("float64", (("lv", "lv"), ("xyz", "3")), None),
    "truth/lv_index": ("int32", (("lv", "lv"), ("field", "3")), None),
    "truth/written": ("uint8", (("turntable", "turntable"), ("camera", "camera")), (1, 1)),
}
FIXED_SIZES = {"3": 3}

#: ``bayer_pattern`` of a capture of demosaicked colour images (``btf import-images``): no mosaic; ``raw``
#: then has a trailing ``channel`` axis of 3 (R, G, B) and the store holds the camera's ``response``.
RGB_PATTERN = "RGB"
#: ``raw`` of an :data:`RGB_PATTERN` capture: ``(n_turn, n_cam, n_illum, n_exp, rows, cols, 3)``.
RAW_RGB_SPEC = ("uint16", ARRAYS["raw"][1] + (("channel", "3"),), (1, 1, 1, "exposure", "row", "col", "3"))
#: ``response`` of an :data:`RGB_PATTERN` capture: each camera's linear inverse response per code and
#: channel (``2**bit_depth`` codes; array attributes ``method`` and ``source``).
RESPONSE_SPEC = ("float64", (("camera", "camera"), ("code", "code"), ("channel", "3")), None)


def raw_spec(bayer_pattern: str | None) -> tuple:
    """The ``raw`` array's (dtype, axes, chunk rule) for a capture with this ``bayer_pattern``."""
    return RAW_RGB_SPEC if bayer_pattern == RGB_PATTERN else ARRAYS["raw"]


def expected_chunks(rule: tuple | None, shape: tuple[int, ...], sizes: Mapping[str, int]) -> tuple[int, ...]:
    """The chunk shape an array of ``shape`` has under its chunk ``rule`` (see :data:`ARRAYS`)."""
    if rule is None:
        return tuple(max(1, int(s)) for s in shape)
    out = []
    for r, s in zip(rule, shape):
        if isinstance(r, int):
            out.append(r)
        else:
            out.append(max(1, int(sizes.get(r, FIXED_SIZES.get(r, s)))))
    return tuple(out)


# --------------------------------------------------------------------------
# Exposure brackets and light/view rows
# --------------------------------------------------------------------------


def trailing_steps_filled(et: np.ndarray) -> np.ndarray:
    """Exposure times with the trailing zeros of a plan capture's shorter brackets (steps not
    taken) replaced by increasing stand-ins, so that a bracket is valid iff its taken steps are
    finite, > 0 and strictly increasing and every step after the first zero is zero too."""
    et = np.asarray(et, dtype=np.float64)
    taken = et != 0
    trailing = np.flip(np.cumsum(np.flip(taken, -1), -1), -1) == 0   # no taken step from here on
    first_ok = taken[..., :1] if et.shape[-1] else taken
    trailing &= np.broadcast_to(first_ok, et.shape)                   # a bracket needs its first step
    with np.errstate(invalid="ignore"):
        top = np.nanmax(np.where(np.isfinite(et), np.abs(et), 0.0), axis=-1, keepdims=True) if et.size else et
    stand_in = top + 1.0 + np.arange(et.shape[-1])
    return np.where(trailing, stand_in, et)


def bracket_steps(et: np.ndarray) -> np.ndarray:
    """Exposure steps taken in each bracket: the leading times > 0 (a plan capture's shorter
    brackets end in zeros)."""
    et = np.asarray(et)
    return np.cumprod(et > 0, axis=-1).sum(axis=-1)


def row_major_lv_index(n_turn: int, n_cam: int, n_leds: int) -> np.ndarray:
    """``(n_lv, 3)`` int32 (turntable, camera, led) in row-major order."""
    g = np.indices((n_turn, n_cam, n_leds)).reshape(3, -1).T
    return g.astype(np.int32)
