"""Rendering a BTF on simple geometry under point and environment light.

Stage 12 (*evaluate*, docs/architecture.md, "Stages") compares BTFs by "PSNR
of renderings under point and environment light". This module renders a
tabulated BTF (rows = light/view pairs, docs/architecture.md, "Matrix
convention") on a sphere, a cylinder or
a plane seen by an orthographic or pinhole camera:

1. per pixel, the first hit of the camera ray, its normal, a tangent frame
   from the surface's ``(u, v)`` parametrisation, texture coordinates with a
   tiling scale and the view direction in the local frame (:func:`surface_geometry`);
2. per pixel and light, the light direction in the local frame and the
   irradiance the light delivers (:class:`PointLight`, :class:`DirectionalLight`,
   an environment map reduced to directional lights by :func:`env_lights`);
3. the BTF value for that light/view pair at that texel: barycentric
   interpolation over the measured views and, per view, over the lights
   measured with it -- the weights of :func:`btfcore.capture.resample.resample_weights`
   (thesis §1.1.2) -- and a nearest or bilinear texel look-up with
   wrap-around (:class:`BTFLookup`);
4. outgoing radiance :math:`L_o = \\sum_k B(l_k, v, x) E_k` (:func:`render_btf`).

Radiometric convention: a stored BTF value already contains the cosine
foreshortening, :math:`B = f_r \\cos\\theta_i` per unit irradiance measured
perpendicular to the light (``docs/btf-store.md``: a white Lambertian sample
of albedo :math:`a` reads :math:`a \\cos\\theta_i / \\pi`), so no cosine is
applied here; lights below the local horizon contribute nothing.

See ``docs/rendering.md``.

References
----------
.. [1] The thesis, §1.1.2 (BTF
   interpolation from 3 x 3 measured light/view pairs).
.. [2] W. Heidrich and H.-P. Seidel, "View-independent environment maps",
   Graphics Hardware 1998 (the parabolic map used for the triangulations).
.. [3] P. Debevec, "Rendering synthetic objects into real scenes", SIGGRAPH
   1998 (lighting with latitude-longitude HDR environment maps).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp

from btfcore.capture.resample import DIRECTION_TOL, barycentric_weights, unique_directions
from btfcore.model.colour import luminance
from btfcore.render.tonemap import tonemap

__all__ = [
    "SHAPES",
    "BTFLookup",
    "Camera",
    "DirectionalLight",
    "EnvLights",
    "Geometry",
    "PointLight",
    "env_directions",
    "env_lights",
    "render_btf",
    "surface_geometry",
    "to_srgb8",
]

#: Geometry :func:`surface_geometry` knows.
SHAPES = ("sphere", "cylinder", "plane")

#: Largest number of (pixel, light) queries whose angular weights :func:`render_btf` computes at once.
_BATCH_QUERIES = 2_000_000
#: Largest number of (query, row, texel) products held at once by :func:`render_btf`.
_BATCH_ENTRIES = 8_000_000


# --------------------------------------------------------------------------- camera and geometry


@dataclass(frozen=True)
class Camera:
    """Camera on the world ``+z`` axis looking down ``-z``; image right is ``+x``, image up ``+y``.

    Parameters
    ----------
    image_shape : (2,) tuple of int
        ``(rows, cols)`` of the image.
    kind : {'orthographic', 'perspective'}
        Parallel rays along ``-z``, or a pinhole at ``(0, 0, distance)``.
    extent : float
        Orthographic: half the width of the view in world units (the objects
        have radius / half-width 1). Perspective: unused.
    distance : float
        Perspective: distance of the pinhole from the origin (> 1).
    fov_deg : float
        Perspective: full vertical field of view in degrees.
    """

    image_shape: tuple[int, int] = (256, 256)
    kind: Literal["orthographic", "perspective"] = "orthographic"
    extent: float = 1.1
    distance: float = 5.0
    fov_deg: float = 30.0

    def __post_init__(self) -> None:
        shape = tuple(int(s) for s in self.image_shape)
        if len(shape) != 2 or min(shape) < 1:
            raise ValueError(f"image_shape must be (rows, cols) of positive ints, got {self.image_shape!r}")
        object.__setattr__(self, "image_shape", shape)
        if self.kind not in ("orthographic", "perspective"):
            raise ValueError(f"kind must be 'orthographic' or 'perspective', got {self.kind!r}")
        if not (math.isfinite(self.extent) and self.extent > 0):
            raise ValueError(f"extent must be a positive number, got {self.extent!r}")
        if self.kind == "perspective":
            if not (math.isfinite(self.distance) and self.distance > 1.0):
                raise ValueError(f"distance must exceed 1 (the objects' radius), got {self.distance!r}")
            if not (0.0 < self.fov_deg < 180.0):
                raise ValueError(f"fov_deg must lie in (0, 180), got {self.fov_deg!r}")

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Origin and unit direction of every pixel's ray, row-major.

        Returns
        -------
        origin, direction : (rows * cols, 3) ndarray of float64
        """
        H, W = self.image_shape
        i, j = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
        aspect = W / H
        sx = ((j.ravel() + 0.5) / W * 2.0 - 1.0) * aspect            # NDC, y up
        sy = 1.0 - (i.ravel() + 0.5) / H * 2.0
        n = H * W
        if self.kind == "orthographic":
            origin = np.stack([sx * self.extent, sy * self.extent, np.full(n, 10.0)], axis=1)
            direction = np.broadcast_to([0.0, 0.0, -1.0], (n, 3)).copy()
        else:
            t = math.tan(math.radians(self.fov_deg) / 2.0)
            direction = np.stack([sx * t, sy * t, -np.ones(n)], axis=1)
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            origin = np.broadcast_to([0.0, 0.0, float(self.distance)], (n, 3)).copy()
        return origin, direction


@dataclass(frozen=True)
class Geometry:
    """What the camera sees at every covered pixel.

    Attributes
    ----------
    mask : (rows, cols) ndarray of bool
        Pixels that see the object.
    pixel : (n,) ndarray of intp
        Row-major index of each covered pixel.
    position, normal, tangent, bitangent : (n, 3) ndarray of float64
        World position and orthonormal local frame ``(x, y, z) =
        (tangent, bitangent, normal)``, right-handed; ``tangent`` points
        along increasing texture column, ``bitangent`` along decreasing
        texture row (the sample frame of the BTF, ``docs/rendering.md``).
    view : (n, 3) ndarray of float64
        Unit direction from the surface point to the camera, world frame.
    texel : (n, 2) ndarray of float64
        Continuous texture coordinate ``(col, row)`` in texels (texel
        ``(i, j)`` is centred at ``(j + 0.5, i + 0.5)``), not yet wrapped.
    """

    mask: np.ndarray
    pixel: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    bitangent: np.ndarray
    view: np.ndarray
    texel: np.ndarray

    def to_local(self, dirs: np.ndarray) -> np.ndarray:
        """World directions ``(n, ..., 3)`` (one set per covered pixel) in each pixel's local frame."""
        d = np.asarray(dirs, dtype=np.float64)
        shape = (len(self.pixel),) + (1,) * (d.ndim - 2) + (3,)
        t, b, n = (a.reshape(shape) for a in (self.tangent, self.bitangent, self.normal))
        return np.stack([(d * t).sum(-1), (d * b).sum(-1), (d * n).sum(-1)], axis=-1)


def _hit_sphere(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Ray parameter of the first hit of the unit sphere (NaN for a miss)."""
    b = np.einsum("ij,ij->i", o, d)
    c = np.einsum("ij,ij->i", o, o) - 1.0
    disc = b * b - c                                                    # eq. |o + t d|^2 = 1
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    return np.where((disc >= 0) & (t > 0), t, np.nan)


def _hit_cylinder(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """First hit of the unit cylinder ``x^2 + z^2 = 1``, ``|y| <= 1`` (outside, no caps)."""
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = o[:, 0] * d[:, 0] + o[:, 2] * d[:, 2]
    c = o[:, 0] ** 2 + o[:, 2] ** 2 - 1.0
    disc = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(disc)) / a
    y = o[:, 1] + t * d[:, 1]
    ok = (a > 1e-12) & (disc >= 0) & (t > 0) & (np.abs(y) <= 1.0)
    return np.where(ok, t, np.nan)


def _hit_plane(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Hit of the square ``[-1, 1]^2`` at ``z = 0`` from the front (``+z``)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        t = -o[:, 2] / d[:, 2]
    x, y = o[:, 0] + t * d[:, 0], o[:, 1] + t * d[:, 1]
    ok = (d[:, 2] < 0) & (t > 0) & (np.abs(x) <= 1.0) & (np.abs(y) <= 1.0)
    return np.where(ok, t, np.nan)


def surface_geometry(
    shape: str,
    camera: Camera,
    tiles: float = 2.0,
    texture_shape: tuple[int, int] = (1, 1),
) -> Geometry:
    """Intersect the camera's rays with a sphere, a cylinder or a plane.

    Parameters
    ----------
    shape : {'sphere', 'cylinder', 'plane'}
        ``sphere``: unit sphere at the origin, poles on the world ``y`` axis;
        ``cylinder``: radius 1 around the ``y`` axis, ``|y| <= 1``, no caps;
        ``plane``: the square ``[-1, 1]^2`` at ``z = 0`` facing ``+z``.
    camera : Camera
    tiles : float
        How many texture tiles span a surface length of 2 (the width of
        every object): one tile is ``2 / tiles`` world units wide.
    texture_shape : (2,) tuple of int
        ``(h, w)`` of the texture; texels are square, so a tile is ``2 h /
        (tiles w)`` units high.

    Returns
    -------
    geometry : Geometry

    Notes
    -----
    Surface coordinates are arc lengths (radius 1), so the texture is not
    stretched along the equator or the cylinder's axis:

    * sphere: :math:`p = (\\sin\\theta \\sin\\phi, \\cos\\theta, \\sin\\theta \\cos\\phi)`,
      :math:`u = \\phi`, :math:`v = \\theta` (the texture shrinks toward the
      poles; the seam :math:`\\phi = \\pm\\pi` faces away from the camera);
    * cylinder: :math:`p = (\\sin\\phi, y, \\cos\\phi)`, :math:`u = \\phi`, :math:`v = 1 - y`;
    * plane: :math:`u = x + 1`, :math:`v = 1 - y`.

    The local frame is :math:`x = \\partial p / \\partial u`,
    :math:`y = -\\partial p / \\partial v` (normalised), :math:`z = n`, and
    the texel coordinate (column, row) is

    .. math:: (c, r) = \\frac{tiles\\, w}{2} (u, v)

    (``tiles`` tiles of ``w`` texels per 2 world units).
    """
    if shape not in SHAPES:
        raise ValueError(f"shape must be one of {SHAPES}, got {shape!r}")
    if not (math.isfinite(tiles) and tiles > 0):
        raise ValueError(f"tiles must be a positive number, got {tiles!r}")
    th, tw = (int(s) for s in texture_shape)
    if th < 1 or tw < 1:
        raise ValueError(f"texture_shape must be (h, w) of positive ints, got {texture_shape!r}")
    o, d = camera.rays()
    t = {"sphere": _hit_sphere, "cylinder": _hit_cylinder, "plane": _hit_plane}[shape](o, d)
    hit = np.isfinite(t)
    pixel = np.flatnonzero(hit)
    p = o[hit] + t[hit, None] * d[hit]
    n_hit = len(pixel)
    if shape == "plane":
        normal = np.broadcast_to([0.0, 0.0, 1.0], (n_hit, 3)).copy()
        tangent = np.broadcast_to([1.0, 0.0, 0.0], (n_hit, 3)).copy()
        bitangent = np.broadcast_to([0.0, 1.0, 0.0], (n_hit, 3)).copy()
        u, v = p[:, 0] + 1.0, 1.0 - p[:, 1]
    else:
        if shape == "sphere":
            normal = p / np.linalg.norm(p, axis=1, keepdims=True)
            theta = np.arccos(np.clip(normal[:, 1], -1.0, 1.0))
            v = theta
        else:
            normal = np.stack([p[:, 0], np.zeros(n_hit), p[:, 2]], axis=1)
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
            v = 1.0 - p[:, 1]
        phi = np.arctan2(normal[:, 0], normal[:, 2])
        u = phi
        tangent = np.stack([np.cos(phi), np.zeros(n_hit), -np.sin(phi)], axis=1)  # eq. dp/du, normalised
        bitangent = np.cross(normal, tangent)                           # eq. y = n x t = -dp/dv
        bitangent /= np.linalg.norm(bitangent, axis=1, keepdims=True)
    view = -d[hit]
    scale = tiles / 2.0 * tw                                            # eq. (c, r) = tiles w / 2 (u, v)
    texel = np.stack([u * scale, v * scale], axis=1)
    mask = hit.reshape(camera.image_shape)
    return Geometry(mask, pixel, p, normal, tangent, bitangent, view, texel)


# --------------------------------------------------------------------------- lights


@dataclass(frozen=True)
class PointLight:
    """Isotropic point light.

    Parameters
    ----------
    position : (3,) tuple of float
        World position (outside the object).
    intensity : (3,) tuple of float
        Radiant intensity per RGB channel; the irradiance at distance
        :math:`r` (perpendicular to the light) is ``intensity / r**2``.
    """

    position: tuple[float, float, float] = (2.0, 2.0, 4.0)
    intensity: tuple[float, float, float] = (24.0, 24.0, 24.0)


@dataclass(frozen=True)
class DirectionalLight:
    """Light from one direction at infinity.

    Parameters
    ----------
    direction : (3,) tuple of float
        World direction *toward* the light (normalised here).
    irradiance : (3,) tuple of float
        RGB irradiance on a surface perpendicular to ``direction``.
    """

    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    irradiance: tuple[float, float, float] = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class EnvLights:
    """An environment map reduced to directional lights.

    Attributes
    ----------
    directions : (k, 3) ndarray of float64
        Unit world directions toward the lights.
    irradiance : (k, 3) ndarray of float64
        RGB irradiance of each light perpendicular to its direction: the
        mean radiance of its part of the map times that part's solid angle.
    """

    directions: np.ndarray
    irradiance: np.ndarray


def env_directions(shape: tuple[int, int], rotation_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """World direction and solid angle of every pixel of a latitude-longitude map.

    Parameters
    ----------
    shape : (2,) tuple of int
        ``(H, W)`` of the map.
    rotation_deg : float
        Turn the map about the world ``y`` axis (positive: the map's
        centre moves toward ``+x``).

    Returns
    -------
    dirs : (H, W, 3) ndarray of float64
    solid_angle : (H,) ndarray of float64
        Solid angle of one pixel of each row (sums to :math:`4\\pi` over the map).

    Notes
    -----
    Row 0 is the zenith (``+y``), row ``H - 1`` the nadir; the centre column
    looks toward ``-z`` (in front of the camera, behind the object) and the
    column increases toward ``+x``:
    :math:`d = (\\sin\\theta \\sin\\phi, \\cos\\theta, -\\sin\\theta \\cos\\phi)`,
    :math:`\\theta = \\pi (i + 1/2) / H`, :math:`\\phi = 2\\pi (j + 1/2) / W - \\pi + \\text{rotation}`.
    """
    H, W = (int(s) for s in shape)
    theta = math.pi * (np.arange(H) + 0.5) / H
    phi = 2.0 * math.pi * (np.arange(W) + 0.5) / W - math.pi + math.radians(rotation_deg)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    dirs = np.stack(np.broadcast_arrays(st * np.sin(phi)[None], ct, -st * np.cos(phi)[None]), axis=-1)
    edges = math.pi * np.arange(H + 1) / H
    solid = (np.cos(edges[:-1]) - np.cos(edges[1:])) * 2.0 * math.pi / W  # eq. dOmega = (cos a - cos b) dphi
    return dirs, solid


def env_lights(env: np.ndarray, n_theta: int = 8, n_phi: int = 16, rotation_deg: float = 0.0) -> EnvLights:
    """Reduce a latitude-longitude HDR environment map to ``n_theta * n_phi`` directional lights.

    Parameters
    ----------
    env : (H, W, 3) array_like
        Linear RGB radiance, non-negative and finite; layout as in
        :func:`env_directions`.
    n_theta, n_phi : int
        Bands of rows and of columns (at most ``H`` and ``W``): every light
        stands for one block of the map.
    rotation_deg : float
        Turn the map about the world ``y`` axis (:func:`env_directions`).

    Returns
    -------
    lights : EnvLights

    Raises
    ------
    ValueError
        On a wrong shape, NaN/Inf or negative radiance (naming the pixel).

    Notes
    -----
    Block :math:`b` gets the irradiance

    .. math:: E_b = \\sum_{p \\in b} L_p\\, \\Delta\\Omega_p

    (the integral of its radiance over its solid angle) and the direction of
    its luminance-weighted centroid (the block's centre when it is black), so
    a small bright source (the sun) keeps its direction. A constant map
    :math:`L` gives :math:`\\sum_b E_b = 4 \\pi L` exactly.
    """
    x = np.asarray(env, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] != 3 or min(x.shape[:2]) < 1:
        raise ValueError(f"env must be an (H, W, 3) RGB map, got shape {x.shape}")
    bad = ~np.isfinite(x) | (x < 0)
    if bad.any():
        idx = tuple(int(v) for v in np.unravel_index(int(np.argmax(bad)), x.shape))
        raise ValueError(f"env{list(idx)} = {float(x[idx])!r}: radiance must be finite and >= 0 "
                         "(clip negative half-float artefacts before)")
    H, W = x.shape[:2]
    if not (1 <= n_theta <= H and 1 <= n_phi <= W):
        raise ValueError(f"n_theta, n_phi = {n_theta}, {n_phi} must lie in 1..{H} and 1..{W} (the map's shape)")
    dirs, solid = env_directions((H, W), rotation_deg)
    weighted = x * solid[:, None, None]                                 # L dOmega per pixel
    lum = luminance(weighted)
    r0 = np.linspace(0, H, n_theta + 1).round().astype(int)[:-1]
    c0 = np.linspace(0, W, n_phi + 1).round().astype(int)[:-1]

    def block_sum(a: np.ndarray) -> np.ndarray:
        return np.add.reduceat(np.add.reduceat(a, r0, axis=0), c0, axis=1)

    irradiance = block_sum(weighted)                                    # eq. E_b = sum L dOmega
    centroid = block_sum(lum[..., None] * dirs)
    centre = block_sum(solid[:, None, None] * dirs)
    norm = np.linalg.norm(centroid, axis=-1, keepdims=True)
    use = norm > 1e-12 * max(float(np.abs(centroid).max(initial=0.0)), 1e-300)
    d = np.where(use, centroid / np.maximum(norm, 1e-300), centre / np.linalg.norm(centre, axis=-1, keepdims=True))
    return EnvLights(d.reshape(-1, 3), irradiance.reshape(-1, 3))


# --------------------------------------------------------------------------- BTF look-up


def _merge_directions(dirs: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    """:func:`btfcore.capture.resample.unique_directions` of many repeated directions, exact repeats merged first."""
    norm = np.linalg.norm(dirs, axis=1)
    bad = ~np.isfinite(norm) | (norm < 1e-12) | ~(dirs[:, 2] >= -1e-9 * norm)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"{name}[{i}] = {dirs[i].tolist()} is not an upper-hemisphere direction "
                         "(finite, non-zero, z >= 0, sample frame)")
    dirs = dirs / norm[:, None]
    key = np.round(dirs * 1e9).astype(np.int64)
    _, first, inv0 = np.unique(key, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)                                           # distinct rows by first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    uniq, inv1 = unique_directions(dirs[first[order]])
    return uniq, inv1[rank[inv0.ravel()]]


class BTFLookup:
    """Angular and spatial interpolation of a tabulated BTF.

    Parameters
    ----------
    btf : (n_lv, h, w, 3) array_like
        Linear RGB BTF, one texture per light/view pair (float32 kept).
    light_dir, view_dir : (n_lv, 3) array_like
        Unit light and view direction of each row, sample frame (z = normal).
    spatial : {'bilinear', 'nearest'}
        Texel look-up; both wrap around (the texture tiles).

    Notes
    -----
    The angular weights are those of
    :func:`btfcore.capture.resample.resample_weights`: the distinct views are
    triangulated in the parabolic map, giving view weights :math:`\\mu_j(v)`;
    the lights measured with each view are triangulated on their own, giving
    :math:`\\lambda^{(j)}_i(l)`; the pair gets :math:`\\mu_j(v)\\lambda^{(j)}_i(l)`,
    at most 3 x 3 rows (thesis §1.1.2). Outside a hull the nearest hull point
    is used (clamped, never extrapolated). Views that share one light set (a
    product sampling, a one-turntable capture) share one light triangulation.
    """

    def __init__(self, btf: np.ndarray, light_dir: np.ndarray, view_dir: np.ndarray,
                 spatial: Literal["bilinear", "nearest"] = "bilinear") -> None:
        B = np.asarray(btf)
        if B.ndim != 4 or B.shape[3] != 3 or min(B.shape) < 1:
            raise ValueError(f"btf must be an (n_lv, h, w, 3) array, got shape {B.shape}")
        if not np.issubdtype(B.dtype, np.floating):
            raise ValueError(f"btf must be floating point (linear radiance), got dtype {B.dtype}")
        L = np.asarray(light_dir, dtype=np.float64)
        V = np.asarray(view_dir, dtype=np.float64)
        for name, a in (("light_dir", L), ("view_dir", V)):
            if a.shape != (B.shape[0], 3):
                raise ValueError(f"{name} has shape {a.shape} but btf has {B.shape[0]} rows: give one "
                                 f"direction per row, ({B.shape[0]}, 3)")
        if spatial not in ("bilinear", "nearest"):
            raise ValueError(f"spatial must be 'bilinear' or 'nearest', got {spatial!r}")
        finite = np.isfinite(B)
        if not finite.all():
            idx = tuple(int(v) for v in np.unravel_index(int(np.argmin(finite)), B.shape))
            raise ValueError(f"btf contains NaN or Inf: btf{list(idx)} = {float(B[idx])!r}")
        self.n_lv, self.h, self.w = B.shape[:3]
        self.spatial = spatial
        self._flat = np.ascontiguousarray(B, dtype=np.float32 if B.dtype == np.float32 else np.float64)
        self._flat = self._flat.reshape(-1, 3)
        self.views, view_inv = _merge_directions(V, "view_dir")
        # the lights measured with each distinct view, grouped by identical light sets
        order = np.argsort(view_inv, kind="stable")
        members = np.split(order, np.cumsum(np.bincount(view_inv, minlength=len(self.views)))[:-1])
        self.light_sets: list[np.ndarray] = []
        self.set_of_view = np.empty(len(self.views), dtype=np.intp)
        rows_of_view: list[np.ndarray] = []
        keys: dict[bytes, int] = {}
        for j, m in enumerate(members):
            lights = L[m]
            key = np.round(lights / DIRECTION_TOL).astype(np.int64).tobytes()
            if key not in keys:
                barycentric_weights(lights, lights[:1])                 # validates the light set
                keys[key] = len(self.light_sets)
                self.light_sets.append(lights)
            self.set_of_view[j] = keys[key]
            rows_of_view.append(m)
        n_max = max(len(m) for m in members)
        self._rows = np.zeros((len(self.views), n_max), dtype=np.intp)  # (view, light-set index) -> row
        for j, m in enumerate(rows_of_view):
            self._rows[j, :len(m)] = m

    # ------------------------------------------------------------------ angular weights

    def view_weights(self, view: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Barycentric weights of query views over the distinct measured views.

        Parameters
        ----------
        view : (n, 3) array_like
            Upper-hemisphere view directions, sample frame.

        Returns
        -------
        index, weight : (n, 3) ndarray of intp and float64
            Distinct-view indices and weights, zero-padded (rows sum to 1).
        """
        W = barycentric_weights(self.views, view).tocsr()
        n = W.shape[0]
        counts = np.diff(W.indptr)
        slot = np.arange(W.nnz) - np.repeat(W.indptr[:-1], counts)
        index = np.zeros((n, 3), dtype=np.intp)
        weight = np.zeros((n, 3))
        r = np.repeat(np.arange(n), counts)
        index[r, slot] = W.indices
        weight[r, slot] = W.data
        return index, weight

    def _entries(self, view_index: np.ndarray, view_weight: np.ndarray, light: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(query, row, weight) triplets of queries with ``(n, 3)`` view weights and ``(n, 3)`` lights."""
        q_all, r_all, w_all = [], [], []
        for g, lights in enumerate(self.light_sets):
            uses = (view_weight > 0) & (self.set_of_view[view_index] == g)   # (n, 3)
            need = np.flatnonzero(uses.any(axis=1))
            if len(need) == 0:
                continue
            lam = barycentric_weights(lights, light[need]).tocoo()          # eq. lambda^(j)_i(l)
            for s in range(3):
                ok = uses[need[lam.row], s]
                q = need[lam.row[ok]]
                j = view_index[q, s]
                q_all.append(q)
                r_all.append(self._rows[j, lam.col[ok]])
                w_all.append(view_weight[q, s] * lam.data[ok])              # eq. mu_j(v) lambda^(j)_i(l)
        if not q_all:
            return np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0)
        return np.concatenate(q_all), np.concatenate(r_all), np.concatenate(w_all)

    def weights(self, light: np.ndarray, view: np.ndarray) -> sp.csr_matrix:
        """Angular interpolation weights of query light/view pairs over the BTF's rows.

        Parameters
        ----------
        light, view : (n, 3) array_like
            Upper-hemisphere directions, sample frame.

        Returns
        -------
        W : (n, n_lv) scipy.sparse.csr_matrix of float64
            Non-negative, rows sum to 1, at most 9 non-zeros per row; the
            same as :func:`btfcore.capture.resample.resample_weights` of this BTF's
            directions and the queries. At a measured pair it is that row.
        """
        light = np.asarray(light, dtype=np.float64)
        view = np.asarray(view, dtype=np.float64)
        if light.shape != view.shape or light.ndim != 2 or light.shape[1] != 3:
            raise ValueError(f"light {light.shape} and view {view.shape} must both be (n, 3)")
        vi, vw = self.view_weights(view)
        q, r, w = self._entries(vi, vw, light)
        W = sp.csr_matrix((w, (q, r)), shape=(len(light), self.n_lv))
        W.sum_duplicates()
        return W

    # ------------------------------------------------------------------ spatial look-up

    def _texels(self, texel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat texel indices and weights ``(n, k)`` (k = 1 nearest, 4 bilinear), wrapped."""
        c, r = texel[:, 0], texel[:, 1]
        if self.spatial == "nearest":
            j = np.floor(c).astype(np.intp) % self.w
            i = np.floor(r).astype(np.intp) % self.h
            return (i * self.w + j)[:, None], np.ones((len(c), 1))
        c, r = c - 0.5, r - 0.5                                         # texel centres at integers
        c0, r0 = np.floor(c), np.floor(r)
        fc, fr = c - c0, r - r0                                         # eq. bilinear fractions
        j0, i0 = c0.astype(np.intp) % self.w, r0.astype(np.intp) % self.h
        j1, i1 = (j0 + 1) % self.w, (i0 + 1) % self.h
        idx = np.stack([i0 * self.w + j0, i0 * self.w + j1, i1 * self.w + j0, i1 * self.w + j1], axis=1)
        wts = np.stack([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc], axis=1)
        return idx, wts

    def lookup(self, light: np.ndarray, view: np.ndarray, texel: np.ndarray) -> np.ndarray:
        """BTF values of query light/view pairs at texture coordinates.

        Parameters
        ----------
        light, view : (n, 3) array_like
            Upper-hemisphere directions, sample frame.
        texel : (n, 2) array_like
            Continuous ``(col, row)`` texture coordinates; texel ``(i, j)``
            is centred at ``(j + 0.5, i + 0.5)``; wrapped around.

        Returns
        -------
        values : (n, 3) ndarray of float64
        """
        light = np.asarray(light, dtype=np.float64)
        texel = np.asarray(texel, dtype=np.float64)
        if texel.shape != (len(light), 2):
            raise ValueError(f"texel must be ({len(light)}, 2) (col, row) coordinates, got {texel.shape}")
        W = self.weights(light, view).tocoo()
        tex, tw = self._texels(texel)
        return self._accumulate(W.row, W.col, W.data, tex, tw, None, len(light))

    def _accumulate(self, q: np.ndarray, row: np.ndarray, w: np.ndarray, tex: np.ndarray, tex_w: np.ndarray,
                    scale: np.ndarray | None, n: int, group: np.ndarray | None = None) -> np.ndarray:
        """Sum ``w * tex_w * B[row, tex] * scale`` per query (or per ``group[q]``) into ``(n, 3)``."""
        out = np.zeros((n, 3))
        target = q if group is None else group[q]                       # pixel (or query) of each entry
        for s in range(tex.shape[1]):
            coef = w * tex_w[target, s]
            vals = self._flat[row * (self.h * self.w) + tex[target, s]].astype(np.float64)  # eq. B(l, v, x)
            vals *= coef[:, None]
            if scale is not None:
                vals *= scale[q]
            for c in range(3):
                out[:, c] += np.bincount(target, weights=vals[:, c], minlength=n)
        return out


# --------------------------------------------------------------------------- rendering


def render_btf(
    lookup: BTFLookup,
    geometry: Geometry,
    lights: PointLight | DirectionalLight | EnvLights | list,
) -> np.ndarray:
    """Render a BTF on a surface under point, directional or environment light.

    Parameters
    ----------
    lookup : BTFLookup
        The BTF with its directions.
    geometry : Geometry
        From :func:`surface_geometry`.
    lights : PointLight, DirectionalLight, EnvLights or list of them
        Summed.

    Returns
    -------
    image : (rows, cols, 3) ndarray of float32
        Linear outgoing radiance; zero where ``geometry.mask`` is False.

    Notes
    -----
    Per covered pixel :math:`x` with local view direction :math:`v`:

    .. math:: L_o(x, v) = \\sum_k B(l_k, v, x)\\, E_k

    where :math:`l_k` is the light direction in the local frame and
    :math:`E_k` the irradiance perpendicular to it: :math:`I / r^2` for a
    point light at distance :math:`r`, the given irradiance for a
    directional light, the block irradiance of :func:`env_lights` for an
    environment map (a Riemann sum of :math:`\\int B(l, v, x) L_{env}(l)\\, dl`).
    The BTF already contains :math:`\\cos\\theta_i` (``docs/btf-store.md``).
    Lights with :math:`l_z \\le 0` (below the local horizon) add nothing;
    the shapes are convex, so nothing else is shadowed. Pixels whose view
    direction is at or below the horizon (silhouette rounding) use the
    view clamped to the horizon.

    Work is vectorised over pixels and batches of lights: the angular
    weights of up to two million (pixel, light) queries are computed in one
    call per light set (each call triangulates once), and at most about
    eight million (query, row, texel) products are held at once.
    """
    items = lights if isinstance(lights, (list, tuple)) else [lights]
    n = len(geometry.pixel)
    rows, cols = geometry.mask.shape
    out = np.zeros((n, 3))
    if n:
        v = geometry.to_local(geometry.view)
        v[:, 2] = np.maximum(v[:, 2], 0.0)
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        vi, vw = lookup.view_weights(v)
        tex, tex_w = lookup._texels(geometry.texel)
        for item in items:
            if isinstance(item, PointLight):
                pos = np.asarray(item.position, dtype=np.float64)
                to = pos[None] - geometry.position
                r2 = np.einsum("ij,ij->i", to, to)
                if np.any(r2 < 1e-12):
                    raise ValueError(f"point light at {item.position} lies on the surface")
                dirs = (to / np.sqrt(r2)[:, None])[:, None]                    # (n, 1, 3)
                irr = (np.asarray(item.intensity, np.float64)[None] / r2[:, None])[:, None]  # eq. E = I / r^2
            elif isinstance(item, DirectionalLight):
                d = np.asarray(item.direction, dtype=np.float64)
                if not np.all(np.isfinite(d)) or np.linalg.norm(d) < 1e-12:
                    raise ValueError(f"DirectionalLight.direction {item.direction} is not a direction")
                dirs = (d / np.linalg.norm(d))[None, None]
                irr = np.asarray(item.irradiance, np.float64)[None, None]
            elif isinstance(item, EnvLights):
                dirs = np.asarray(item.directions, np.float64)[None]
                irr = np.asarray(item.irradiance, np.float64)[None]
            else:
                raise ValueError(f"lights must be PointLight, DirectionalLight or EnvLights, got {type(item).__name__}")
            k_total = dirs.shape[1]
            batch = max(1, _BATCH_QUERIES // n)                          # lights per weight computation
            for k0 in range(0, k_total, batch):
                dk = dirs[:, k0:k0 + batch]
                ek = irr[:, k0:k0 + batch]
                local = geometry.to_local(np.broadcast_to(dk, (n,) + dk.shape[1:]))  # (n, kb, 3)
                # lights above the local horizon, light-major: neighbouring queries are neighbouring
                # pixels, so the point location in the triangulation walks only a few triangles
                kk, pix = np.nonzero(local[..., 2].T > 0)
                if len(pix) == 0:
                    continue
                e = np.broadcast_to(ek, (n,) + ek.shape[1:])[pix, kk]   # (m, 3)
                q, row, w = lookup._entries(vi[pix], vw[pix], local[pix, kk])
                step = max(1, _BATCH_ENTRIES // tex.shape[1])
                for a in range(0, len(q), step):
                    sl = slice(a, a + step)
                    out += lookup._accumulate(q[sl], row[sl], w[sl], tex, tex_w, e, n, group=pix)
    image = np.zeros((rows * cols, 3), dtype=np.float32)
    image[geometry.pixel] = out
    return image.reshape(rows, cols, 3)


def to_srgb8(image: np.ndarray, mask: np.ndarray | None = None, white: float | None = None,
             background: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
    """Tone-map a linear rendering to 8-bit sRGB (:func:`btfcore.render.tonemap.tonemap`).

    Parameters
    ----------
    image : (rows, cols, 3) ndarray
        Linear radiance.
    mask : (rows, cols) ndarray of bool, optional
        Covered pixels: the white point is taken from them only and the
        rest is painted ``background``.
    white : float, optional
        Radiance mapped to white; the 99.5th percentile of the covered
        pixels when omitted.
    background : (3,) tuple of int
        RGB of uncovered pixels.

    Returns
    -------
    rgb : (rows, cols, 3) ndarray of uint8
    """
    x = np.asarray(image, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"image must be (rows, cols, 3), got shape {x.shape}")
    if mask is None:
        return tonemap(x, white=white)
    m = np.asarray(mask, dtype=bool)
    if m.shape != x.shape[:2]:
        raise ValueError(f"mask has shape {m.shape} but image {x.shape[:2]}")
    if white is None:
        covered = x[m]
        positive = covered[covered > 0]
        white = float(np.percentile(positive, 99.5)) if positive.size else 1.0
    out = tonemap(x, white=white)
    out[~m] = np.asarray(background, dtype=np.uint8)
    return out
