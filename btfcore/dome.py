"""Camera-dome device presets: geometry of lights, cameras and turntable, and the sensor.

A :class:`Device` is everything about a measurement dome that does not depend
on the material: LED and camera positions, pinhole intrinsics and extrinsics,
turntable angles, the raw region of interest (ROI), the sample and texture
size, the sensor (:class:`SensorSpec`) and the per-LED intensity/colour that a
radiometric calibration must measure.

Conventions (fixed; the rest of the pipeline relies on them)
-------------------------------------------------------------
* World frame: z up, sample centre at the origin, sample in the plane z = 0.
  ``theta`` is measured from +z, ``phi`` from +x counter-clockwise.
* The turntable rotates the sample by ``a`` about z: ``p_world = Rz(a) p_sample``;
  a direction in the sample frame is ``d_s = Rz(-a) d_w``.
* The sample is the square ``[-s/2, s/2]^2`` (``s = sample_size_m``) of the
  sample frame; texel ``(i, j)`` of an ``(h, w)`` texture is centred at
  ``x = ((j + 0.5) / w - 0.5) s``, ``y = (0.5 - (i + 0.5) / h) s``.
* Lights are directional at the sample (direction from the origin to the LED).
* Cameras are pinholes looking at the origin; a world point ``X`` has camera
  coordinates ``R X + t`` (x right, y down, z forward, OpenCV), pixel
  ``K (R X + t)``. Pixel centres ``(col, row)`` are integers. The image "down"
  axis is the world +x axis projected onto the image plane, so a camera on the
  ``phi = 0`` meridian sees world up as image up, and the frontal camera sees
  sample +x downwards and sample +y to the right. Only cameras at
  ``phi = 180 deg`` near the horizon would make this degenerate (refused).
* ``camera_K`` is expressed on the ROI pixel grid; the sample centre projects
  to the ROI centre ``((cols - 1) / 2, (rows - 1) / 2)``.
* ``H[t, c] = K [r1 r2 t] A(a)`` maps sample-plane metres ``(x, y, 1)`` to ROI
  pixels ``(col, row, 1)``; ``A(a)`` is the planar turntable rotation and
  ``r1, r2`` the first two columns of ``camera_R``.

See ``docs/devices.md`` for the presets and the sensor model.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "BAYER_PATTERNS",
    "DEVICE_NAMES",
    "Device",
    "SensorSpec",
    "camera_pose_look_at",
    "get_device",
    "ring_directions",
    "spherical_to_cartesian",
]

BAYER_PATTERNS: tuple[str, ...] = ("RGGB", "BGGR", "GRBG", "GBRG")
DEVICE_NAMES: tuple[str, ...] = ("tiny", "bonn-dome2", "ubo-dome1")


# --------------------------------------------------------------------------- sensor


@dataclass(frozen=True, eq=False)
class SensorSpec:
    """A linear raw camera sensor (see :mod:`btfcore.simulate.sensor`).

    Parameters
    ----------
    bayer_pattern : {'RGGB', 'BGGR', 'GRBG', 'GBRG'}
        Colour filter of the 2x2 top-left block of the raw frame, read row-major.
    bit_depth : int
        ADC bit depth, 1..16; raw values lie in ``[0, 2**bit_depth - 1]``.
    black_level : int
        DN offset added to every pixel.
    gain_e_per_dn : float
        Electrons per DN (the inverse system gain).
    read_noise_e : float
        Standard deviation of the Gaussian read noise, electrons.
    full_well_e : float
        Pixel capacity, electrons; signal saturates there.
    dark_current_e_per_s : float
        Mean dark current, electrons per second; the per-pixel fixed pattern
        is drawn by :func:`btfcore.simulate.sensor.dark_current_map`.
    sensitivity_rgb : (3,) tuple of float
        Electrons per second per unit of BTF radiance for the R, G, B filters
        (lens, LED power and quantum efficiency folded together). With the
        defaults a diffuse texel of BTF value 0.1 fills 80 % of the well of a
        green pixel in ~0.09 s, a glossy highlight of 100 in ~0.1 ms and a
        shadow of 1e-3 reaches 5 % in ~0.5 s: exposures of milliseconds to
        seconds as in a real dome.
    psf_sigma_px : float
        Standard deviation of a Gaussian point-spread function in raw pixels,
        applied per colour plane before the mosaic; 0 disables it.
    n_exposures : int
        Length of the exposure bracket of every frame.
    """

    bayer_pattern: str = "RGGB"
    bit_depth: int = 12
    black_level: int = 64
    gain_e_per_dn: float = 1.5
    read_noise_e: float = 3.0
    full_well_e: float = 5500.0
    dark_current_e_per_s: float = 5.0
    sensitivity_rgb: tuple[float, float, float] = (3.0e5, 5.0e5, 2.5e5)
    psf_sigma_px: float = 0.0
    n_exposures: int = 3

    def __post_init__(self) -> None:
        object.__setattr__(self, "sensitivity_rgb", tuple(float(v) for v in self.sensitivity_rgb))
        problems = []
        if self.bayer_pattern not in BAYER_PATTERNS:
            problems.append(f"bayer_pattern {self.bayer_pattern!r} is not one of {', '.join(BAYER_PATTERNS)}")
        if not (1 <= int(self.bit_depth) <= 16):
            problems.append(f"bit_depth must be in 1..16, got {self.bit_depth}")
        if not (self.gain_e_per_dn > 0 and math.isfinite(self.gain_e_per_dn)):
            problems.append(f"gain_e_per_dn must be finite and > 0, got {self.gain_e_per_dn}")
        if not (self.full_well_e > 0 and math.isfinite(self.full_well_e)):
            problems.append(f"full_well_e must be finite and > 0, got {self.full_well_e}")
        if not (self.read_noise_e >= 0 and math.isfinite(self.read_noise_e)):
            problems.append(f"read_noise_e must be finite and >= 0, got {self.read_noise_e}")
        if not (self.dark_current_e_per_s >= 0 and math.isfinite(self.dark_current_e_per_s)):
            problems.append(f"dark_current_e_per_s must be finite and >= 0, got {self.dark_current_e_per_s}")
        if len(self.sensitivity_rgb) != 3 or not all(v > 0 and math.isfinite(v) for v in self.sensitivity_rgb):
            problems.append(f"sensitivity_rgb must be 3 finite values > 0, got {self.sensitivity_rgb}")
        if not (self.psf_sigma_px >= 0 and math.isfinite(self.psf_sigma_px)):
            problems.append(f"psf_sigma_px must be finite and >= 0, got {self.psf_sigma_px}")
        if int(self.n_exposures) < 1:
            problems.append(f"n_exposures must be >= 1, got {self.n_exposures}")
        if not problems and not (0 <= int(self.black_level) < self.white_level):
            problems.append(
                f"black_level {self.black_level} must be >= 0 and below the white level {self.white_level} "
                f"(min(2**bit_depth - 1, black_level + full_well_e / gain_e_per_dn))"
            )
        if problems:
            raise ValueError("invalid SensorSpec: " + "; ".join(problems))

    @property
    def max_dn(self) -> int:
        """Largest value the ADC can output, ``2**bit_depth - 1``."""
        return (1 << int(self.bit_depth)) - 1

    @property
    def white_level(self) -> int:
        """DN at which the sensor saturates.

        ``min(2**bit_depth - 1, black_level + floor(full_well_e / gain_e_per_dn))``.
        """
        return int(min(self.max_dn, int(self.black_level) + math.floor(self.full_well_e / self.gain_e_per_dn)))

    def replace(self, **changes: Any) -> "SensorSpec":
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON dict of the fields (and the derived ``white_level``)."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["sensitivity_rgb"] = [float(v) for v in self.sensitivity_rgb]
        for key in ("bit_depth", "black_level", "n_exposures"):
            d[key] = int(d[key])
        for key in ("gain_e_per_dn", "read_noise_e", "full_well_e", "dark_current_e_per_s", "psf_sigma_px"):
            d[key] = float(d[key])
        d["white_level"] = self.white_level
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "SensorSpec":
        """Inverse of :meth:`to_json` (derived keys are ignored)."""
        names = {f.name for f in dataclasses.fields(cls)}
        kw = {k: v for k, v in d.items() if k in names}
        if "sensitivity_rgb" in kw:
            kw["sensitivity_rgb"] = tuple(kw["sensitivity_rgb"])
        return cls(**kw)


# --------------------------------------------------------------------------- geometry helpers


def spherical_to_cartesian(theta_deg: np.ndarray, phi_deg: np.ndarray, radius: float = 1.0) -> np.ndarray:
    """Points on a sphere from polar and azimuthal angles.

    Parameters
    ----------
    theta_deg, phi_deg : (n,) array_like
        Polar angle from +z and azimuth from +x (counter-clockwise), degrees.
    radius : float
        Sphere radius.

    Returns
    -------
    xyz : (n, 3) ndarray of float64
        ``radius * (sin t cos p, sin t sin p, cos t)``.
    """
    t = np.deg2rad(np.asarray(theta_deg, dtype=np.float64))
    p = np.deg2rad(np.asarray(phi_deg, dtype=np.float64))
    return radius * np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def ring_directions(thetas_deg, counts, offsets_deg=None) -> tuple[np.ndarray, np.ndarray]:
    """Polar/azimuth angles of directions on rings of constant theta.

    Parameters
    ----------
    thetas_deg : (k,) array_like
        Polar angle of each ring.
    counts : (k,) array_like of int
        Directions per ring, evenly spaced in azimuth.
    offsets_deg : (k,) array_like, optional
        Azimuth of the first direction of each ring (default 0).

    Returns
    -------
    theta_deg, phi_deg : (n,) ndarray of float64
        ``n = sum(counts)``, ring by ring; ``phi`` in ``[0, 360)``.
    """
    counts = [int(c) for c in counts]
    offsets = np.zeros(len(counts)) if offsets_deg is None else np.asarray(offsets_deg, dtype=np.float64)
    theta = np.concatenate([np.full(c, float(t)) for t, c in zip(thetas_deg, counts)])
    phi = np.concatenate([(o + 360.0 * np.arange(c) / c) % 360.0 for o, c in zip(offsets, counts)])
    return theta, phi


def camera_pose_look_at(position: np.ndarray, down_hint=(1.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """World->camera rotations and translations of cameras looking at the origin.

    Parameters
    ----------
    position : (n, 3) ndarray
        Camera centres, world frame, metres.
    down_hint : (3,) array_like
        World direction that should point down the image (+row); it is
        projected onto each image plane. The default, world +x, gives image
        up = world up for cameras on the ``phi = 0`` meridian and is valid at
        ``theta = 0``.

    Returns
    -------
    R : (n, 3, 3) ndarray
        Rows are the camera axes x (right), y (down), z (forward) in world
        coordinates; orthonormal with det +1.
    t : (n, 3) ndarray
        ``t = -R C``, so that ``X_cam = R X + t``.

    Notes
    -----
    .. math::
        z_c = -C/|C|, \\quad y_c \\propto d - (d \\cdot z_c) z_c, \\quad
        x_c = y_c \\times z_c
    """
    C = np.asarray(position, dtype=np.float64)
    z = -C / np.linalg.norm(C, axis=1, keepdims=True)                    # eq. forward axis
    d = np.asarray(down_hint, dtype=np.float64)
    d = d / np.linalg.norm(d)
    y = d[None, :] - (z @ d)[:, None] * z                                # eq. down axis
    norm = np.linalg.norm(y, axis=1)
    if np.any(norm < 0.05):
        bad = np.flatnonzero(norm < 0.05).tolist()
        raise ValueError(f"cameras {bad} look along the image-down hint {d.tolist()}; choose another down_hint")
    y /= norm[:, None]
    x = np.cross(y, z)                                                   # eq. right axis
    R = np.stack([x, y, z], axis=1)
    t = -np.einsum("nij,nj->ni", R, C)                                   # eq. t = -R C
    return R, t


def _rz(a_rad: np.ndarray) -> np.ndarray:
    c, s = np.cos(a_rad), np.sin(a_rad)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _as_array(value, dtype, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.array(value, dtype=dtype, copy=True)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise ValueError(f"Device.{name} must have shape (n, {', '.join(map(str, shape_tail))}), got {arr.shape}"
                         if shape_tail else f"Device.{name} must be 1-D, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"Device.{name} contains NaN or Inf at {np.argwhere(~np.isfinite(arr))[0].tolist()}")
    arr.setflags(write=False)
    return arr


# --------------------------------------------------------------------------- device


@dataclass(frozen=True, eq=False)
class Device:
    """Geometry, sensor and light calibration of a camera dome.

    Parameters
    ----------
    name : str
        Preset name or a free label.
    led_position : (n_leds, 3) ndarray of float64
        LED positions, world frame, metres, z > 0.
    camera_position : (n_cam, 3) ndarray of float64
        Camera centres, world frame, metres.
    camera_K : (n_cam, 3, 3) ndarray of float64
        Intrinsics on the ROI pixel grid.
    camera_R : (n_cam, 3, 3) ndarray of float64
        World -> camera rotations.
    camera_t : (n_cam, 3) ndarray of float64
        Translations, ``X_cam = R X + t``.
    turntable_angle_deg : (n_turn,) ndarray of float64
        Turntable angles, degrees.
    roi_shape : (2,) tuple of int
        ``(rows, cols)`` of the raw region of interest.
    sample_size_m : float
        Side of the square sample, metres.
    texture_shape : (2,) tuple of int
        ``(h, w)`` of the rectified texture.
    sensor : SensorSpec
        The cameras' sensor (all cameras alike).
    lights_are_flashes : bool
        True when the lights are the cameras' flashes (``led_position`` equals
        ``camera_position``).
    led_rgb_gain : (n_leds, 3) ndarray of float64
        Intensity and colour of each LED relative to nominal, per RGB channel:
        the unknown that a radiometric calibration must measure. Ones when
        omitted.
    """

    name: str
    led_position: np.ndarray
    camera_position: np.ndarray
    camera_K: np.ndarray
    camera_R: np.ndarray
    camera_t: np.ndarray
    turntable_angle_deg: np.ndarray
    roi_shape: tuple[int, int]
    sample_size_m: float
    texture_shape: tuple[int, int]
    sensor: SensorSpec = field(default_factory=SensorSpec)
    lights_are_flashes: bool = False
    led_rgb_gain: np.ndarray | None = None

    def __post_init__(self) -> None:
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731
        set_("led_position", _as_array(self.led_position, np.float64, (3,), "led_position"))
        set_("camera_position", _as_array(self.camera_position, np.float64, (3,), "camera_position"))
        set_("camera_K", _as_array(self.camera_K, np.float64, (3, 3), "camera_K"))
        set_("camera_R", _as_array(self.camera_R, np.float64, (3, 3), "camera_R"))
        set_("camera_t", _as_array(self.camera_t, np.float64, (3,), "camera_t"))
        set_("turntable_angle_deg", _as_array(self.turntable_angle_deg, np.float64, (), "turntable_angle_deg"))
        gain = np.ones((len(self.led_position), 3)) if self.led_rgb_gain is None else self.led_rgb_gain
        set_("led_rgb_gain", _as_array(gain, np.float64, (3,), "led_rgb_gain"))
        set_("roi_shape", tuple(int(v) for v in self.roi_shape))
        set_("texture_shape", tuple(int(v) for v in self.texture_shape))
        set_("sample_size_m", float(self.sample_size_m))
        problems = []
        n_cam, n_leds = len(self.camera_position), len(self.led_position)
        for name in ("camera_K", "camera_R", "camera_t"):
            if len(getattr(self, name)) != n_cam:
                problems.append(f"{name} has {len(getattr(self, name))} cameras, camera_position {n_cam}")
        if len(self.led_rgb_gain) != n_leds:
            problems.append(f"led_rgb_gain has {len(self.led_rgb_gain)} rows for {n_leds} LEDs")
        elif np.any(self.led_rgb_gain <= 0):
            problems.append("led_rgb_gain must be > 0")
        if n_cam == 0 or n_leds == 0 or len(self.turntable_angle_deg) == 0:
            problems.append(f"need at least one camera, LED and turntable angle (got {n_cam}, {n_leds}, "
                            f"{len(self.turntable_angle_deg)})")
        if n_leds and np.any(self.led_position[:, 2] <= 0):
            problems.append(f"LEDs {np.flatnonzero(self.led_position[:, 2] <= 0).tolist()} are not above the sample")
        if len(self.roi_shape) != 2 or min(self.roi_shape) < 1:
            problems.append(f"roi_shape must be two positive ints, got {self.roi_shape}")
        if len(self.texture_shape) != 2 or min(self.texture_shape) < 1:
            problems.append(f"texture_shape must be two positive ints, got {self.texture_shape}")
        if not (self.sample_size_m > 0 and math.isfinite(self.sample_size_m)):
            problems.append(f"sample_size_m must be finite and > 0, got {self.sample_size_m}")
        if not isinstance(self.sensor, SensorSpec):
            problems.append(f"sensor must be a SensorSpec, got {type(self.sensor).__name__}")
        if n_cam and len(self.camera_R) == n_cam:
            err = np.abs(self.camera_R @ np.swapaxes(self.camera_R, 1, 2) - np.eye(3)).max(axis=(1, 2))
            det = np.linalg.det(self.camera_R)
            bad = np.flatnonzero((err > 1e-6) | (np.abs(det - 1) > 1e-6))
            if bad.size:
                problems.append(f"camera_R of cameras {bad.tolist()} is not a rotation")
        if self.lights_are_flashes and (self.led_position.shape != self.camera_position.shape
                                        or not np.allclose(self.led_position, self.camera_position)):
            problems.append("lights_are_flashes requires led_position == camera_position")
        if problems:
            raise ValueError(f"invalid Device {self.name!r}: " + "; ".join(problems))

    # ------------------------------------------------------------------ sizes

    @property
    def n_turn(self) -> int:
        """Number of turntable positions."""
        return int(len(self.turntable_angle_deg))

    @property
    def n_cam(self) -> int:
        """Number of cameras."""
        return int(len(self.camera_position))

    @property
    def n_leds(self) -> int:
        """Number of light sources."""
        return int(len(self.led_position))

    @property
    def n_lv(self) -> int:
        """Number of light/view pairs, ``n_turn * n_cam * n_leds``."""
        return self.n_turn * self.n_cam * self.n_leds

    # ------------------------------------------------------------------ geometry

    def turntable_rotation(self, t: int) -> np.ndarray:
        """``Rz(a_t)``, (3, 3): sample frame -> world frame."""
        return _rz(np.deg2rad(self.turntable_angle_deg[t]))

    def homographies(self) -> np.ndarray:
        """All sample-plane -> ROI homographies.

        Returns
        -------
        H : (n_turn, n_cam, 3, 3) ndarray of float64

        Notes
        -----
        .. math:: H_{tc} = K_c \\, [r_1 \\; r_2 \\; t_c] \\, A(a_t)

        with :math:`r_1, r_2` the first two columns of :math:`R_c` and
        :math:`A(a)` the planar rotation by the turntable angle (sample ->
        world), embedded in 3x3 with a unit bottom-right entry.
        """
        P = np.concatenate([self.camera_R[:, :, :2], self.camera_t[:, :, None]], axis=2)  # [r1 r2 t]
        A = _rz(np.deg2rad(self.turntable_angle_deg))                                       # (n_turn, 3, 3)
        return np.einsum("cij,cjk,tkl->tcil", self.camera_K, P, A)                          # eq. H = K[r1 r2 t]A

    def homography(self, t: int, c: int) -> np.ndarray:
        """Sample-plane metres ``(x, y, 1)`` -> ROI pixel ``(col, row, 1)`` of view ``(t, c)``, (3, 3)."""
        P = np.concatenate([self.camera_R[c][:, :2], self.camera_t[c][:, None]], axis=1)
        return self.camera_K[c] @ P @ self.turntable_rotation(t)                             # eq. H = K[r1 r2 t]A

    def project(self, points_sample: np.ndarray, t: int, c: int) -> np.ndarray:
        """Full pinhole projection of 3-D sample-frame points.

        Parameters
        ----------
        points_sample : (n, 3) ndarray
            Points in the sample frame, metres.

        Returns
        -------
        pixels : (n, 2) ndarray
            ``(col, row)`` in the ROI.
        """
        X = np.asarray(points_sample, dtype=np.float64) @ self.turntable_rotation(t).T      # p_w = Rz(a) p_s
        q = (X @ self.camera_R[c].T + self.camera_t[c]) @ self.camera_K[c].T                 # eq. K (R X + t)
        return q[:, :2] / q[:, 2:3]

    def light_dirs(self, t: int) -> np.ndarray:
        """Unit directions from the sample centre to the LEDs in the sample frame at turntable position ``t``.

        Returns
        -------
        dirs : (n_leds, 3) ndarray of float64
        """
        d = self.led_position / np.linalg.norm(self.led_position, axis=1, keepdims=True)
        return d @ self.turntable_rotation(t)                                  # eq. d_s = Rz(-a) d_w

    def view_dir(self, t: int, c: int) -> np.ndarray:
        """Unit direction from the sample centre to camera ``c`` in the sample frame, (3,)."""
        d = self.camera_position[c] / np.linalg.norm(self.camera_position[c])
        return self.turntable_rotation(t).T @ d                                # eq. d_s = Rz(-a) d_w

    def view_dirs(self, t: int) -> np.ndarray:
        """All cameras' view directions at turntable position ``t``, (n_cam, 3)."""
        d = self.camera_position / np.linalg.norm(self.camera_position, axis=1, keepdims=True)
        return d @ self.turntable_rotation(t)

    def lv_directions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Light and view direction of every light/view pair.

        Returns
        -------
        light_dir : (n_lv, 3) ndarray of float64
            Unit, sample frame.
        view_dir : (n_lv, 3) ndarray of float64
            Unit, sample frame.
        lv_index : (n_lv, 3) ndarray of int32
            ``(turntable, camera, light)`` of each row; rows are flattened
            row-major over ``(turntable, camera, light)``:
            ``lv = (t * n_cam + c) * n_leds + l``.
        """
        n_t, n_c, n_l = self.n_turn, self.n_cam, self.n_leds
        L = np.stack([self.light_dirs(t) for t in range(n_t)])                 # (n_t, n_l, 3)
        V = np.stack([self.view_dirs(t) for t in range(n_t)])                  # (n_t, n_c, 3)
        light = np.broadcast_to(L[:, None], (n_t, n_c, n_l, 3)).reshape(-1, 3).copy()
        view = np.broadcast_to(V[:, :, None], (n_t, n_c, n_l, 3)).reshape(-1, 3).copy()
        idx = np.stack(np.meshgrid(np.arange(n_t), np.arange(n_c), np.arange(n_l), indexing="ij"), -1)
        return light, view, idx.reshape(-1, 3).astype(np.int32)

    # ------------------------------------------------------------------ derived copies

    def with_overrides(self, **kw: Any) -> "Device":
        """A copy with some fields replaced.

        Parameters
        ----------
        **kw
            Any :class:`Device` field. Special cases:

            * ``sensor``: a :class:`SensorSpec`, or a dict of sensor fields to
              change (e.g. ``sensor={"psf_sigma_px": 0.7}``);
            * ``bayer_pattern``: shortcut for ``sensor={"bayer_pattern": ...}``;
            * ``roi_shape``: the principal points are shifted so that the
              sample centre stays at the centre of the new ROI;
            * ``turntable_angle_deg``: any subset or new set of angles;
            * ``camera_indices`` / ``led_indices``: keep only these cameras /
              LEDs (positions, poses and gains follow);
            * ``pixel_scale``: an int ``f >= 1``, the same dome whose cameras
              have ``f`` times the pixels along each axis (applied after the
              other overrides): ``K' = S K`` with
              ``S = [[f, 0, (f - 1) / 2], [0, f, (f - 1) / 2], [0, 0, 1]]`` and
              ``roi_shape`` times ``f``, so that a pixel of the original camera
              covers exactly the ``f x f`` block of the new camera's pixels
              (pixel centre ``x`` -> ``f x + (f - 1) / 2``). The sensor, and
              its PSF in raw pixels, stay as they are.

        Returns
        -------
        device : Device
        """
        kw = dict(kw)
        pixel_scale = kw.pop("pixel_scale", None)
        if pixel_scale is not None:
            return self.with_overrides(**kw)._with_pixel_scale(pixel_scale)
        sensor = kw.pop("sensor", None)
        pattern = kw.pop("bayer_pattern", None)
        if isinstance(sensor, dict):
            sensor = self.sensor.replace(**sensor)
        sensor = sensor if sensor is not None else self.sensor
        if pattern is not None:
            sensor = sensor.replace(bayer_pattern=pattern)
        kw["sensor"] = sensor
        cams = kw.pop("camera_indices", None)
        leds = kw.pop("led_indices", None)
        if cams is not None:
            cams = np.asarray(cams, dtype=np.int64)
            for name in ("camera_position", "camera_K", "camera_R", "camera_t"):
                kw.setdefault(name, getattr(self, name)[cams])
            if self.lights_are_flashes and leds is None:
                leds = cams
        if leds is not None:
            leds = np.asarray(leds, dtype=np.int64)
            kw.setdefault("led_position", self.led_position[leds])
            kw.setdefault("led_rgb_gain", self.led_rgb_gain[leds])
        if "roi_shape" in kw:
            rows, cols = (int(v) for v in kw["roi_shape"])
            K = np.array(kw.get("camera_K", self.camera_K), dtype=np.float64)
            K[:, 0, 2] += (cols - self.roi_shape[1]) / 2.0
            K[:, 1, 2] += (rows - self.roi_shape[0]) / 2.0
            kw["camera_K"] = K
        unknown = set(kw) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise TypeError(f"unknown Device field(s) {sorted(unknown)}")
        return dataclasses.replace(self, **kw)

    def _with_pixel_scale(self, f: Any) -> "Device":
        """The same dome with ``f`` times the camera pixels along each axis (:meth:`with_overrides`)."""
        if isinstance(f, bool) or not isinstance(f, (int, np.integer)) or f < 1:
            raise ValueError(f"pixel_scale must be an integer >= 1, got {f!r}")
        f = int(f)
        if f == 1:
            return self
        return dataclasses.replace(self, camera_K=pixel_scale_matrix(f) @ self.camera_K,   # eq. K' = S K
                                   roi_shape=(f * self.roi_shape[0], f * self.roi_shape[1]))

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON dict (arrays as nested lists)."""
        return {
            "name": self.name,
            "led_position": self.led_position.tolist(),
            "camera_position": self.camera_position.tolist(),
            "camera_K": self.camera_K.tolist(),
            "camera_R": self.camera_R.tolist(),
            "camera_t": self.camera_t.tolist(),
            "turntable_angle_deg": self.turntable_angle_deg.tolist(),
            "roi_shape": list(self.roi_shape),
            "sample_size_m": self.sample_size_m,
            "texture_shape": list(self.texture_shape),
            "sensor": self.sensor.to_json(),
            "lights_are_flashes": bool(self.lights_are_flashes),
            "led_rgb_gain": self.led_rgb_gain.tolist(),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "Device":
        """Inverse of :meth:`to_json`."""
        kw = dict(d)
        kw["sensor"] = SensorSpec.from_json(kw["sensor"])
        return cls(**kw)


# --------------------------------------------------------------------------- presets


def _device_rng(name: str) -> np.random.Generator:
    """Fixed generator of one physical device (LED gains): the same on every machine."""
    return np.random.default_rng([20151270, zlib.crc32(name.encode())])


def _led_gains(name: str, n_leds: int) -> np.ndarray:
    """Per-LED RGB gain: intensity ~ N(1, 0.05) times colour ~ N(1, 0.02) per channel."""
    rng = _device_rng(name)
    intensity = rng.normal(1.0, 0.05, size=(n_leds, 1))
    colour = rng.normal(1.0, 0.02, size=(n_leds, 3))
    return np.clip(intensity * colour, 0.5, 1.5)


def pixel_scale_matrix(factor: float) -> np.ndarray:
    """``S`` with ``x' = S x`` taking pixel coordinates of a camera to those of one with ``factor`` times
    the pixels per axis: ``[[f, 0, (f - 1) / 2], [0, f, (f - 1) / 2], [0, 0, 1]]``, so that a pixel of the
    first covers exactly the ``f x f`` block of the second (pixel centre ``x -> f x + (f - 1) / 2``; a
    factor below 1 is the area-down-sampled camera)."""
    f = float(factor)
    if not f > 0:
        raise ValueError(f"the pixel scale factor must be > 0, got {factor!r}")
    return np.array([[f, 0.0, (f - 1) / 2.0], [0.0, f, (f - 1) / 2.0], [0.0, 0.0, 1.0]])


def _fit_roi(K: np.ndarray, R: np.ndarray, t: np.ndarray, angles_deg: np.ndarray, s: float,
             multiple: int = 8, margin: int = 2) -> tuple[int, int]:
    """Smallest ROI (multiple of ``multiple``) containing the sample at every view with a margin.

    ``K`` has its principal point at 0 (the sample centre's projection).
    """
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64) * s / 2
    ext = 0.0, 0.0
    for a in np.deg2rad(angles_deg):
        ca, sa = math.cos(a), math.sin(a)
        Xw = np.stack([ca * corners[:, 0] - sa * corners[:, 1], sa * corners[:, 0] + ca * corners[:, 1],
                       np.zeros(4)], axis=1)
        q = np.einsum("cij,cjk,nk->cni", K, R, Xw) + np.einsum("cij,cj->ci", K, t)[:, None]
        px = q[..., :2] / q[..., 2:3]                                            # (n_cam, 4, 2) col,row
        ext = max(ext[0], float(np.abs(px[..., 1]).max())), max(ext[1], float(np.abs(px[..., 0]).max()))
    # a corner at offset e from the centre (c - 1) / 2 must satisfy e + 0.5 + margin <= (c - 1) / 2 + 0.5
    size = [int(math.ceil((2 * (e + margin) + 1) / multiple) * multiple) for e in ext]
    return size[0], size[1]


def _build(name: str, cam_theta, cam_phi, led_theta, led_phi, *, radius: float, sample_size_m: float,
           frontal_px: float, turntable_deg, texture_shape, sensor: SensorSpec,
           lights_are_flashes: bool = False, roi_shape: tuple[int, int] | None = None) -> Device:
    cam_pos = spherical_to_cartesian(cam_theta, cam_phi, radius)
    led_pos = cam_pos.copy() if lights_are_flashes else spherical_to_cartesian(led_theta, led_phi, radius)
    R, t = camera_pose_look_at(cam_pos)
    f = frontal_px * radius / sample_size_m          # eq. sample spans frontal_px at distance radius
    K = np.tile(np.array([[f, 0.0, 0.0], [0.0, f, 0.0], [0.0, 0.0, 1.0]]), (len(cam_pos), 1, 1))
    turntable = np.asarray(turntable_deg, dtype=np.float64)
    if roi_shape is None:
        roi_shape = _fit_roi(K, R, t, turntable, sample_size_m)
    K[:, 0, 2] = (roi_shape[1] - 1) / 2.0            # sample centre -> ROI centre
    K[:, 1, 2] = (roi_shape[0] - 1) / 2.0
    return Device(name=name, led_position=led_pos, camera_position=cam_pos, camera_K=K, camera_R=R, camera_t=t,
                  turntable_angle_deg=turntable, roi_shape=roi_shape, sample_size_m=sample_size_m,
                  texture_shape=texture_shape, sensor=sensor, lights_are_flashes=lights_are_flashes,
                  led_rgb_gain=_led_gains(name, len(led_pos)))


def _angular_distance_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise angles between unit vectors ``a`` (n, 3) and ``b`` (m, 3), degrees."""
    return np.rad2deg(np.arccos(np.clip(a @ b.T, -1.0, 1.0)))


def _spread_rings(n_total: int, thetas: np.ndarray, avoid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``n_total`` directions on rings at ``thetas``, counts ~ sin(theta), azimuth offsets that keep
    away from the unit directions ``avoid`` (cameras, opposite LEDs)."""
    w = np.sin(np.deg2rad(thetas))
    counts = np.maximum(1, np.floor(n_total * w / w.sum())).astype(int)
    while counts.sum() < n_total:       # largest remainders first
        counts[np.argmax(n_total * w / w.sum() - counts)] += 1
    while counts.sum() > n_total:
        counts[np.argmax(counts)] -= 1
    theta_all, phi_all = [], []
    for th, n in zip(thetas, counts):
        best, best_off = -1.0, 0.0
        for off in np.linspace(0.0, 360.0 / n, 24, endpoint=False):
            th_r, ph_r = ring_directions([th], [n], [off])
            d = _angular_distance_deg(spherical_to_cartesian(th_r, ph_r), avoid).min()
            if d > best + 1e-9:
                best, best_off = d, off
        th_r, ph_r = ring_directions([th], [n], [best_off])
        theta_all.append(th_r)
        phi_all.append(ph_r)
    return np.concatenate(theta_all), np.concatenate(phi_all)


def _tiny(sensor: SensorSpec) -> Device:
    cam_theta = np.array([0.0, 25.0, 50.0, 75.0])
    cam_phi = np.zeros(4)
    # 13 LEDs on four rings, azimuths offset from the camera meridian, down to a
    # grazing 80 deg ring as on a real dome (long cast shadows), plus 3 LEDs
    # exactly opposite the cameras at 25/50/75 deg (mirror reflection).
    ring_t, ring_p = ring_directions([15.0, 40.0, 65.0, 80.0], [3, 4, 3, 3], [60.0, 45.0, 30.0, 90.0])
    led_theta = np.concatenate([ring_t, cam_theta[1:]])
    led_phi = np.concatenate([ring_p, np.full(3, 180.0)])
    return _build("tiny", cam_theta, cam_phi, led_theta, led_phi, radius=0.65, sample_size_m=0.05,
                  frontal_px=48.0, turntable_deg=[0.0, 120.0, 240.0], texture_shape=(32, 32),
                  sensor=sensor)


def _bonn_dome2(sensor: SensorSpec) -> Device:
    cam_theta = np.arange(11) * 7.5                  # 0, 7.5, ..., 75 deg on one meridian
    cam_phi = np.zeros(11)
    opp_theta, opp_phi = cam_theta[1:], np.full(10, 180.0)   # opposite the 10 lowest cameras
    avoid = np.concatenate([spherical_to_cartesian(cam_theta, cam_phi),
                            spherical_to_cartesian(opp_theta, opp_phi)])
    ring_theta = 3.75 + 7.5 * np.arange(12)          # rings midway between the camera elevations
    rt, rp = _spread_rings(188, ring_theta, avoid)
    return _build("bonn-dome2", cam_theta, cam_phi, np.concatenate([opp_theta, rt]),
                  np.concatenate([opp_phi, rp]), radius=0.65, sample_size_m=0.05, frontal_px=200.0,
                  turntable_deg=np.arange(12) * 30.0, texture_shape=(128, 128),
                  sensor=sensor.replace(n_exposures=4))


#: Rings of the fully parallel 151-camera dome: (theta deg, count, azimuth offset deg).
UBO_DOME1_RINGS: tuple[tuple[float, int, float], ...] = (
    (0.0, 1, 0.0), (11.0, 6, 15.0), (23.5, 12, 0.0), (30.0, 12, 15.0), (37.5, 12, 0.0),
    (45.0, 18, 0.0), (52.5, 18, 7.5), (60.0, 24, 0.0), (67.5, 24, 7.5), (75.0, 24, 0.0),
)


def _ubo_dome1(sensor: SensorSpec) -> Device:
    th, n, off = zip(*UBO_DOME1_RINGS)
    cam_theta, cam_phi = ring_directions(th, n, off)
    return _build("ubo-dome1", cam_theta, cam_phi, None, None, radius=0.65, sample_size_m=0.04,
                  frontal_px=160.0, turntable_deg=[0.0], texture_shape=(128, 128), sensor=sensor,
                  lights_are_flashes=True)


_PRESETS = {"tiny": _tiny, "bonn-dome2": _bonn_dome2, "ubo-dome1": _ubo_dome1}


def get_device(name: str, *, bayer_pattern: str | None = None, **overrides: Any) -> Device:
    """A device preset.

    Parameters
    ----------
    name : {'tiny', 'bonn-dome2', 'ubo-dome1'}
        ``tiny``: 4 cameras x 16 LEDs x 3 turntable positions, 32x32 texels
        (tests); ``bonn-dome2``: the semi-parallel dome of the thesis, 11
        cameras x 198 LEDs x 12 turntable positions; ``ubo-dome1``: the fully
        parallel 151-camera dome whose flashes are the lights.
    bayer_pattern : str, optional
        Override the sensor's Bayer layout.
    **overrides
        Passed to :meth:`Device.with_overrides` (e.g. ``texture_shape``,
        ``sensor``, ``turntable_angle_deg``, ``roi_shape``).

    Returns
    -------
    device : Device

    Raises
    ------
    ValueError
        For an unknown name (the message lists the valid ones).
    """
    if name not in _PRESETS:
        raise ValueError(f"unknown device {name!r}; valid devices: {', '.join(DEVICE_NAMES)}")
    device = _PRESETS[name](SensorSpec())
    if bayer_pattern is not None:
        overrides["bayer_pattern"] = bayer_pattern
    return device.with_overrides(**overrides) if overrides else device
