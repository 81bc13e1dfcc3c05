"""Ground-truth BTF renderer for height-field materials.

The BTF value of a texel for a light direction ``l`` and a view direction
``v`` is the radiance leaving the sample toward ``v`` from the point that
the camera sees through the texel's point on the reference plane, for a
distant light of unit irradiance measured perpendicular to ``l``.  It
therefore includes ``cos(theta_i)``: a flat white Lambertian of albedo ``a``
gives ``a / pi * cos(theta_i)``.

The work is split in two:

* :func:`prepare_view` (once per view) marches the view ray through every
  texel's reference-plane point against the height field (first hit from
  above, refined by bisection and a final secant step): parallax and
  masking.  It samples normal, albedo, roughness, specular weight and the
  horizon map at the hit point and precomputes every light-independent
  term.
* :func:`shade` (per light, ``O(H W)`` vectorised, no marching) evaluates
  Lambert + GGX at the local normal, the cast-shadow visibility from the
  interpolated horizon map with the soft edge of an LED of finite angular
  size, and a small one-bounce indirect term.

Geometry conventions: the sample frame has ``z`` up, the map grid's pixel
``(i, j)`` is centred at ``x = (j + 0.5)/W - 0.5``, ``y = 0.5 - (i + 0.5)/H``
(units of the sample side), heights are in units of the column pitch
``side / W``; the reference plane is at the mean height.  Outside the map the
height field and all other maps continue by *mirror reflection* about the
map's border (half-sample symmetric), so no seam appears and photographs need
not be tileable.  See ``docs/simulator-physics.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from btfcore.simulate.materials import MaterialMaps

__all__ = [
    "LED_ANGULAR_RADIUS_DEG",
    "HORIZON_MIN_ELEVATION_DEG",
    "INDIRECT_SCALE",
    "SurfaceView",
    "horizon_map",
    "prepare_view",
    "shade",
    "render_view",
    "downsample2",
]

#: Angular radius (degrees) of an LED seen from the sample: sets the width of
#: the shadow penumbra (a 1.7 cm diffuser at 1 m subtends about 0.5 deg).
LED_ANGULAR_RADIUS_DEG = 0.5

#: Lowest horizon elevation (degrees) the default ``max_distance`` of
#: :func:`horizon_map` resolves exactly.
HORIZON_MIN_ELEVATION_DEG = 3.0

#: Weight of the one-bounce indirect term.  A modelling choice, not a
#: measured constant: it keeps inter-reflection a small correction to the
#: direct light (see docs/simulator-physics.md, "Indirect light").
INDIRECT_SCALE = 0.5

#: Smallest view elevation sine accepted by :func:`prepare_view`.
_MIN_VIEW_Z = 1e-3


# ---------------------------------------------------------------------------
# sampling helpers (mirror boundary)
# ---------------------------------------------------------------------------


def _fold(u: np.ndarray, n: int) -> np.ndarray:
    """Reflect pixel-index coordinates into ``[-0.5, n - 0.5]`` (period ``2 n``)."""
    p = np.mod(u + 0.5, 2 * n)
    p = np.where(p >= n, 2 * n - p, p)
    return p - 0.5


def _bilinear_setup(r: np.ndarray, c: np.ndarray, H: int, W: int):
    """Flat indices and weights of bilinear interpolation at ``(r, c)``."""
    r = _fold(r, H)
    c = _fold(c, W)
    r0f = np.floor(r)
    c0f = np.floor(c)
    fr = (r - r0f).astype(np.float32)
    fc = (c - c0f).astype(np.float32)
    r0 = r0f.astype(np.intp)
    c0 = c0f.astype(np.intp)
    r1 = np.minimum(r0 + 1, H - 1)
    c1 = np.minimum(c0 + 1, W - 1)
    np.maximum(r0, 0, out=r0)
    np.maximum(c0, 0, out=c0)
    idx = (r0 * W + c0, r0 * W + c1, r1 * W + c0, r1 * W + c1)
    w = ((1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc)
    return idx, w


def _gather(img: np.ndarray, setup) -> np.ndarray:
    """Bilinear sample of ``img`` (H, W, ...) at a setup from :func:`_bilinear_setup`."""
    idx, w = setup
    flat = img.reshape((-1,) + img.shape[2:])
    extra = (Ellipsis,) + (None,) * (img.ndim - 2)
    out = flat[idx[0]] * w[0][extra]
    for k in range(1, 4):
        out += flat[idx[k]] * w[k][extra]
    return out


def _mirror_extend(h: np.ndarray) -> np.ndarray:
    """``(3H + 1, 3W + 1)`` mirror extension: one full period ``(2H, 2W)`` plus a map."""
    H, W = h.shape
    return np.pad(h, ((0, 2 * H + 1), (0, 2 * W + 1)), mode="symmetric")


def _shift_sample(hext: np.ndarray, dr: float, dc: float, out: np.ndarray, tmp: np.ndarray) -> np.ndarray:
    """Bilinear sample of the mirrored map at ``(i + dr, j + dc)`` for every pixel.

    The offset is the same for all pixels, so bilinear interpolation is a
    weighted sum of four shifted slices of :func:`_mirror_extend`'s array
    (the mirrored map is periodic with period ``(2H, 2W)``, so any offset,
    however large, is reduced modulo the period).
    """
    H, W = out.shape
    r0 = math.floor(dr)
    c0 = math.floor(dc)
    fr = dr - r0
    fc = dc - c0
    r = r0 % (2 * H)
    c = c0 % (2 * W)
    a = hext[r : r + H, c : c + W]
    if fr == 0.0 and fc == 0.0:
        np.copyto(out, a)
        return out
    b = hext[r : r + H, c + 1 : c + 1 + W]
    np.multiply(a, (1 - fr) * (1 - fc), out=out)
    np.multiply(b, (1 - fr) * fc, out=tmp)
    out += tmp
    if fr != 0.0:
        cc = hext[r + 1 : r + 1 + H, c : c + W]
        d = hext[r + 1 : r + 1 + H, c + 1 : c + 1 + W]
        np.multiply(cc, fr * (1 - fc), out=tmp)
        out += tmp
        np.multiply(d, fr * fc, out=tmp)
        out += tmp
    return out


def _check_height(height) -> np.ndarray:
    h = np.asarray(height, dtype=np.float32)
    if h.ndim != 2 or min(h.shape) < 2:
        raise ValueError(f"height must be an (H, W) array with H, W >= 2, got shape {h.shape}")
    if not np.all(np.isfinite(h)):
        raise ValueError("height contains NaN or Inf")
    return h


def _unit(d, name: str) -> np.ndarray:
    v = np.asarray(d, dtype=np.float64)
    if v.shape[-1:] != (3,):
        raise ValueError(f"{name} must have a last axis of length 3, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} contains NaN or Inf")
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise ValueError(f"{name} contains a zero-length direction")
    return v / n


# ---------------------------------------------------------------------------
# horizon map
# ---------------------------------------------------------------------------


def horizon_map(
    height: np.ndarray,
    n_azimuth: int = 32,
    max_distance: float | None = None,
) -> np.ndarray:
    """Horizon elevation of a height field in ``n_azimuth`` directions.

    Parameters
    ----------
    height : (H, W) ndarray
        Height field in column-pitch units (``side / W``).
    n_azimuth : int
        Number of azimuths ``phi_k = 2 pi k / n_azimuth``, measured in the
        sample frame from ``+x`` toward ``+y``.
    max_distance : float, optional
        Search radius in column pitches.  Default: the distance at which the
        map's full height range subtends :data:`HORIZON_MIN_ELEVATION_DEG`,
        at most ``max(H, W)``.

    Returns
    -------
    horizon : (n_azimuth, H, W) ndarray of float32
        Horizon elevation angle in radians, in ``[0, pi/2)``.

    Notes
    -----
    For every pixel ``p`` and azimuth ``phi`` the heights along
    ``p + s (cos phi, sin phi)`` are sampled at ``s = 1, 2, ..., max_distance``
    pitches (bilinear, mirror boundary) and

    .. math:: \\eta(p, \\phi) = \\arctan \\max\\Big(0, \\max_s \\frac{h(p + s d_\\phi) - h(p)}{s}\\Big)

    The elevation is clipped at 0: beyond the search radius the surface is
    assumed to continue at no more than the reference level.  Because the
    offset ``s d_phi`` is the same for all pixels, each sample is four shifted
    slices of the padded map.  The search of one azimuth stops early once no
    farther point can raise any pixel's horizon, i.e. when
    ``tan(eta) s >= max(h) - h`` everywhere.
    """
    h = _check_height(height)
    n_azimuth = int(n_azimuth)
    if n_azimuth < 4:
        raise ValueError(f"n_azimuth must be >= 4, got {n_azimuth}")
    H, W = h.shape
    ry = H / W  # rows per column pitch
    span = float(h.max() - h.min())
    if max_distance is None:
        md = span / math.tan(math.radians(HORIZON_MIN_ELEVATION_DEG))
        n_steps = int(np.clip(math.ceil(md), 1, max(H, W)))
    else:
        if not (max_distance >= 1):
            raise ValueError(f"max_distance must be >= 1 pitch, got {max_distance}")
        n_steps = int(math.ceil(max_distance))
    out = np.zeros((n_azimuth, H, W), np.float32)
    if span == 0.0:
        return out
    hext = _mirror_extend(h)
    room = np.float32(h.max()) - h  # eq. stop test: tan(eta) * s >= max(h) - h
    best = np.empty((H, W), np.float32)
    smp = np.empty((H, W), np.float32)
    tmp = np.empty((H, W), np.float32)
    for k in range(n_azimuth):
        phi = 2.0 * math.pi * k / n_azimuth
        cx, cy = math.cos(phi), math.sin(phi)
        best.fill(0.0)
        for s in range(1, n_steps + 1):
            _shift_sample(hext, -s * cy * ry, s * cx, smp, tmp)
            smp -= h
            smp *= np.float32(1.0 / s)  # eq. slope (h(p + s d) - h(p)) / s
            np.maximum(best, smp, out=best)
            if s % 8 == 0 and s < n_steps:
                np.multiply(best, np.float32(s), out=tmp)
                if np.all(tmp >= room):
                    break
        np.arctan(best, out=out[k])
    return out


# ---------------------------------------------------------------------------
# per-view precomputation
# ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SurfaceView:
    """Everything about one view that does not depend on the light.

    Made by :func:`prepare_view`; consumed by :func:`shade`.  All maps are
    indexed by the texel ``(i, j)`` through whose reference-plane point the
    camera looks; their values belong to the surface point actually seen.

    Attributes
    ----------
    view_dir : (3,) ndarray of float64
        Unit direction toward the camera.
    z_ref : float
        Height of the reference plane (mean height), column pitches.
    hit_row, hit_col : (H, W) ndarray of float64
        Map-index coordinates of the seen point (pixel centres at integers;
        may lie outside the map, which continues by mirror reflection).
    hit_height : (H, W) ndarray of float32
        Height of the seen point.
    normal : (3, H, W) ndarray of float32
        Unit surface normal ``(n_x, n_y, n_z)`` at the seen point.
    albedo : (H, W, 3) ndarray of float32
        Diffuse albedo at the seen point.
    roughness, specular : (H, W) ndarray of float32
        GGX alpha and specular weight at the seen point.
    f0 : (3,) ndarray of float32
        Fresnel reflectance at normal incidence.
    horizon : (n_az, H, W) ndarray of float32
        Horizon elevation (radians) at the seen point per azimuth.
    horizon_max : (n_az,) ndarray of float32
        Largest value of each horizon slice (lets :func:`shade` skip the
        shadow test for lights above every horizon).
    occlusion : (H, W) ndarray of float32
        ``1 - V_sky``: cosine-weighted fraction of the local hemisphere
        blocked by the surface, in ``[0, 1]``.
    mean_albedo : (3,) ndarray of float32
        Mean albedo of the whole material (colour of the inter-reflected light).
    n_dot_v : (H, W) ndarray of float32
        ``max(n . v, 0)``.
    light_radius : float
        Angular radius of the LED (radians).
    albedo_over_pi, indirect : (H, W, 3) ndarray of float32
        ``albedo / pi`` and ``albedo / pi * mean_albedo * occlusion``.
    alpha2, spec_scale : (H, W) ndarray of float32
        ``roughness**2`` and ``specular / Lambda_v`` (see Notes of :func:`shade`).
    has_specular : bool
        Whether any texel has a specular weight > 0.
    grid_normal : (3, n_g) ndarray of float32
        Normals at a regular subsample of the map's own pixels (at most about
        4096, independent of the view): the surface whose mean direct
        irradiance feeds the indirect term.
    grid_horizon : (n_az, n_g) ndarray of float32
        Horizon elevations at the same pixels.
    """

    view_dir: np.ndarray
    z_ref: float
    hit_row: np.ndarray
    hit_col: np.ndarray
    hit_height: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    roughness: np.ndarray
    specular: np.ndarray
    f0: np.ndarray
    horizon: np.ndarray
    horizon_max: np.ndarray
    occlusion: np.ndarray
    mean_albedo: np.ndarray
    n_dot_v: np.ndarray
    light_radius: float
    albedo_over_pi: np.ndarray
    indirect: np.ndarray
    alpha2: np.ndarray
    spec_scale: np.ndarray
    has_specular: bool
    grid_normal: np.ndarray
    grid_horizon: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """Texel grid ``(H, W)``."""
        return self.hit_height.shape  # type: ignore[return-value]


def _march(h: np.ndarray, v: np.ndarray, z_ref: float, step: float, n_bisect: int):
    """First intersection from above of each texel's view ray with the height field.

    Returns the ray parameter ``t`` (column pitches along ``v``) per texel.
    """
    H, W = h.shape
    ry = H / W
    vx, vy, vz = (float(c) for c in v)
    hmin, hmax = float(h.min()), float(h.max())
    eps = 1e-4 * max(1.0, hmax - hmin)
    t_top = (hmax + eps - z_ref) / vz  # ray above every height
    t_bot = (hmin - eps - z_ref) / vz  # ray below every height
    speed = max(math.hypot(vx, vy * ry), vz)
    n = max(1, int(math.ceil((t_top - t_bot) * speed / step)))
    n = min(n, 8192)
    dt = (t_top - t_bot) / n
    hext = _mirror_extend(h)

    smp = np.empty((H, W), np.float32)
    tmp = np.empty((H, W), np.float32)
    d_prev = np.empty((H, W), np.float32)
    d_cur = np.empty((H, W), np.float32)
    found = np.zeros((H, W), bool)
    newly = np.empty((H, W), bool)
    k_hit = np.zeros((H, W), np.int32)
    d_lo = np.zeros((H, W), np.float32)
    d_hi = np.zeros((H, W), np.float32)

    _shift_sample(hext, -t_top * vy * ry, t_top * vx, smp, tmp)
    np.subtract(np.float32(z_ref + t_top * vz), smp, out=d_prev)
    for k in range(1, n + 1):
        t = t_top - k * dt
        _shift_sample(hext, -t * vy * ry, t * vx, smp, tmp)
        np.subtract(np.float32(z_ref + t * vz), smp, out=d_cur)  # ray height - surface height
        np.less_equal(d_cur, 0.0, out=newly)
        newly &= ~found
        np.copyto(k_hit, k, where=newly)
        np.copyto(d_lo, d_cur, where=newly)
        np.copyto(d_hi, d_prev, where=newly)
        found |= newly
        d_prev, d_cur = d_cur, d_prev
        if k % 8 == 0 and found.all():
            break
    # bracket: t_lo (on/below the surface, d <= 0) < t_hi (above, d > 0)
    k_hit = k_hit.astype(np.float64)
    t_lo = t_top - k_hit * dt
    t_hi = t_lo + dt
    d_lo = d_lo.astype(np.float64)
    d_hi = d_hi.astype(np.float64)
    ii, jj = np.indices((H, W), dtype=np.float64)
    for _ in range(n_bisect):  # bisection on the per-texel bracket
        tm = 0.5 * (t_lo + t_hi)
        hm = _gather(h, _bilinear_setup(ii - tm * vy * ry, jj + tm * vx, H, W))
        dm = z_ref + tm * vz - hm
        below = dm <= 0
        t_lo = np.where(below, tm, t_lo)
        d_lo = np.where(below, dm, d_lo)
        t_hi = np.where(below, t_hi, tm)
        d_hi = np.where(below, d_hi, dm)
    denom = d_hi - d_lo  # > 0 by construction
    frac = np.where(denom > 0, -d_lo / np.where(denom > 0, denom, 1.0), 0.0)
    return t_lo + (t_hi - t_lo) * np.clip(frac, 0.0, 1.0)  # secant (false position) step


def _sky_visibility(horizon: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Cosine-weighted visible-sky fraction ``V_sky`` from horizons and normals."""
    n_az = horizon.shape[0]
    nx, ny, nz = (normal[c].astype(np.float64) for c in range(3))
    acc = np.zeros(nx.shape, np.float64)
    for k in range(n_az):
        phi = 2.0 * math.pi * k / n_az
        nt = nx * math.cos(phi) + ny * math.sin(phi)
        e0 = np.arctan2(-nt, nz)  # eq. lower limit where n . w >= 0
        g = np.maximum(horizon[k].astype(np.float64), e0)
        acc += nt * (0.25 * np.pi - 0.5 * g - 0.25 * np.sin(2 * g)) + 0.5 * nz * np.cos(g) ** 2  # eq. sector integral
    return np.clip(acc * (2.0 / n_az), 0.0, 1.0)  # eq. V = (dphi / pi) * sum


def _normals(h: np.ndarray, horizon: np.ndarray, setup) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals at the seen points (``(3, H, W)``, bilinear from central differences of the height field),
    and the normals and horizons ``(3, n_g)``, ``(n_az, n_g)`` at a regular subsample of the map's pixels."""
    H, W = h.shape
    ry = H / W
    hp1 = np.pad(h, 1, mode="symmetric")
    dh_dcol = 0.5 * (hp1[1:-1, 2:] - hp1[1:-1, :-2])
    dh_drow = 0.5 * (hp1[2:, 1:-1] - hp1[:-2, 1:-1])
    stride = max(1, int(round(math.sqrt(H * W / 4096.0))))
    o = stride // 2
    ggx = dh_dcol[o::stride, o::stride].ravel()
    ggy = -dh_drow[o::stride, o::stride].ravel() * np.float32(ry)
    ginv = 1.0 / np.sqrt(ggx * ggx + ggy * ggy + 1.0)
    grid_normal = np.stack([-ggx * ginv, -ggy * ginv, ginv]).astype(np.float32)
    grid_horizon = np.ascontiguousarray(horizon[:, o::stride, o::stride].reshape(horizon.shape[0], -1))
    gx = _gather(dh_dcol, setup)  # dh/dx (x: +col, pitch units)
    gy = -_gather(dh_drow, setup) * np.float32(ry)  # dh/dy (y: -row)
    inv = 1.0 / np.sqrt(gx * gx + gy * gy + 1.0)
    normal = np.stack([-gx * inv, -gy * inv, inv]).astype(np.float32)  # eq. n ~ (-h_x, -h_y, 1)
    return normal, grid_normal, grid_horizon


def prepare_view(
    maps: MaterialMaps,
    view_dir: np.ndarray,
    horizon: np.ndarray | None = None,
    *,
    light_radius_deg: float = LED_ANGULAR_RADIUS_DEG,
    step: float = 0.5,
    n_bisect: int = 5,
) -> SurfaceView:
    """Precompute everything of a view that does not depend on the light.

    Parameters
    ----------
    maps : MaterialMaps
        The material.
    view_dir : (3,) array_like
        Direction toward the camera (normalised here); ``z`` must be > 0.
    horizon : (n_az, H, W) ndarray, optional
        :func:`horizon_map` of ``maps.height`` (computed here when omitted;
        pass it when rendering several views of one material).
    light_radius_deg : float
        Angular radius of the LEDs (soft shadow edge).
    step : float
        March step along the ray, in column pitches of horizontal (or
        vertical, if larger) travel.
    n_bisect : int
        Bisection steps refining the bracketed hit before the final secant.

    Returns
    -------
    view : SurfaceView

    Notes
    -----
    The ray through texel ``(i, j)`` leaves its reference-plane point
    ``p_0 = (j, i, z_ref)`` (column, row, height) toward the camera:

    .. math:: p(t) = \\big(j + t v_x,\\; i - t v_y H/W,\\; z_{ref} + t v_z\\big)

    and is marched downward from ``t_top`` (above the highest point) in steps
    of ``step`` pitches until it is first at or below the surface (the first
    hit from above, which is the visible point); the bracket is refined by
    bisection and a secant step.  Normals come from central differences of
    the height field (mirror boundary), interpolated bilinearly:

    .. math:: n \\propto (-\\partial h/\\partial x, -\\partial h/\\partial y, 1)

    The visible-sky fraction uses the horizon ``eta_k`` of each azimuth
    sector and the local normal, with ``n_t = n_x cos phi_k + n_y sin phi_k``
    and ``g = max(eta_k, arctan2(-n_t, n_z))``:

    .. math:: V_{sky} = \\frac{\\Delta\\phi}{\\pi} \\sum_k \\Big[ n_t \\Big(\\frac{\\pi}{4}
              - \\frac{g}{2} - \\frac{\\sin 2g}{4}\\Big) + \\frac{n_z}{2}\\cos^2 g \\Big]
    """
    if not isinstance(maps, MaterialMaps):
        raise TypeError(f"maps must be a MaterialMaps, got {type(maps).__name__}")
    v = _unit(view_dir, "view_dir").reshape(3)
    if v[2] < _MIN_VIEW_Z:
        raise ValueError(f"view_dir must point above the sample (z > {_MIN_VIEW_Z}), got {v.tolist()}")
    h = maps.height
    H, W = h.shape
    if horizon is None:
        horizon = horizon_map(h)
    horizon = np.asarray(horizon, dtype=np.float32)
    if horizon.ndim != 3 or horizon.shape[1:] != (H, W) or horizon.shape[0] < 4:
        raise ValueError(f"horizon must be (n_az, {H}, {W}) with n_az >= 4, got {horizon.shape}")
    ry = H / W
    z_ref = float(h.mean(dtype=np.float64))  # reference plane: mean height

    t = _march(h, v, z_ref, float(step), int(n_bisect))
    ii, jj = np.indices((H, W), dtype=np.float64)
    hit_row = ii - t * v[1] * ry
    hit_col = jj + t * v[0]
    hit_height = (z_ref + t * v[2]).astype(np.float32)
    setup = _bilinear_setup(hit_row, hit_col, H, W)
    normal, grid_normal, grid_horizon = _normals(h, horizon, setup)

    albedo = np.clip(_gather(maps.albedo, setup), 0.0, 1.0).astype(np.float32)
    rough = np.clip(_gather(maps.roughness, setup), 1e-3, 1.0).astype(np.float32)
    spec = np.maximum(_gather(maps.specular, setup), 0.0).astype(np.float32)
    hz = _gather(np.moveaxis(horizon, 0, -1), setup)
    hz = np.ascontiguousarray(np.moveaxis(hz, -1, 0), dtype=np.float32)

    occlusion = (1.0 - _sky_visibility(hz, normal)).astype(np.float32)
    mean_albedo = maps.albedo.mean(axis=(0, 1), dtype=np.float64).astype(np.float32)
    ndv = np.clip(normal[0] * v[0] + normal[1] * v[1] + normal[2] * v[2], 0.0, 1.0).astype(np.float32)
    alpha2 = (rough * rough).astype(np.float32)
    lam_v = ndv + np.sqrt(alpha2 + (1.0 - alpha2) * ndv * ndv)  # eq. Lambda_v (Smith, separable)
    albedo_pi = (albedo / np.float32(np.pi)).astype(np.float32)
    return SurfaceView(
        view_dir=v,
        z_ref=z_ref,
        hit_row=hit_row,
        hit_col=hit_col,
        hit_height=hit_height,
        normal=normal,
        albedo=albedo,
        roughness=rough,
        specular=spec,
        f0=maps.f0.astype(np.float32),
        horizon=hz,
        horizon_max=hz.reshape(hz.shape[0], -1).max(axis=1),
        occlusion=occlusion,
        mean_albedo=mean_albedo,
        n_dot_v=ndv,
        light_radius=math.radians(float(light_radius_deg)),
        albedo_over_pi=albedo_pi,
        indirect=(albedo_pi * (INDIRECT_SCALE * mean_albedo) * occlusion[..., None]).astype(np.float32),  # eq. one bounce
        alpha2=alpha2,
        spec_scale=(spec / lam_v).astype(np.float32),
        has_specular=bool(np.any(spec > 0)),
        grid_normal=grid_normal,
        grid_horizon=grid_horizon,
    )


# ---------------------------------------------------------------------------
# per-light shading
# ---------------------------------------------------------------------------


def _disc_visibility(elev: float, horizon: np.ndarray, delta: float) -> np.ndarray:
    """Fraction of an LED disc of angular radius ``delta`` above ``horizon``."""
    u = np.clip((elev - horizon) * (1.0 / delta), -1.0, 1.0)
    return 0.5 + (u * np.sqrt(1.0 - u * u) + np.arcsin(u)) * (1.0 / math.pi)  # eq. disc fraction


def _mean_irradiance(view: SurfaceView, l: np.ndarray, elev: float, k0: int, k1: int, w: float) -> float:
    """Mean direct irradiance ``E_bar`` of the material's surface for one light."""
    gn = view.grid_normal
    nl = np.maximum(gn[0] * l[0] + gn[1] * l[1] + gn[2] * l[2], 0.0)
    hz = view.grid_horizon[k0] * (1.0 - w) + view.grid_horizon[k1] * w
    return float(np.mean(nl * _disc_visibility(elev, hz, view.light_radius), dtype=np.float64))


def shade(view: SurfaceView, light_dirs: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """BTF values of one prepared view for a set of distant lights.

    Parameters
    ----------
    view : SurfaceView
        From :func:`prepare_view`.
    light_dirs : (n_l, 3) array_like
        Directions toward the lights (normalised here).  Lights at or below
        the sample plane (``z <= 0``) give 0.
    out : (n_l, H, W, 3) ndarray of float32, optional
        Output buffer.

    Returns
    -------
    btf : (n_l, H, W, 3) ndarray of float32
        Radiance toward the camera for unit irradiance perpendicular to
        each light; finite and ``>= 0``.

    Notes
    -----
    With ``n`` the local normal, ``l`` the light, ``v`` the view,
    ``h = (l + v)/|l + v|``, ``alpha`` the roughness, ``k_s`` the specular
    weight, ``rho`` the albedo, ``rho_bar`` the material's mean albedo and
    ``V`` the light visibility:

    .. math::

        L = \\Big(\\frac{\\rho}{\\pi} + k_s \\frac{D\\,F}{\\Lambda_l \\Lambda_v}\\Big)
            \\max(n \\cdot l, 0)\\, V
            + s_{ind} \\frac{\\rho}{\\pi}\\, \\bar\\rho\\, (1 - V_{sky})\\, \\bar E

    .. math::

        D = \\frac{\\alpha^2}{\\pi\\,((n \\cdot h)^2(\\alpha^2 - 1) + 1)^2}, \\quad
        \\Lambda_x = n \\cdot x + \\sqrt{\\alpha^2 + (1 - \\alpha^2)(n \\cdot x)^2}, \\quad
        F = F_0 + (1 - F_0)(1 - v \\cdot h)^5

    ``D F / (Lambda_l Lambda_v)`` equals the GGX microfacet BRDF
    ``D F G / (4 (n.l)(n.v))`` with the separable Smith ``G = G_1(l) G_1(v)``,
    ``G_1(x) = 2 (n.x) / Lambda_x``, written without the divisions by the
    cosines so that it stays finite at grazing angles.  The visibility is the
    area fraction of the LED's disc (angular radius ``delta``) above the
    horizon ``eta`` (interpolated linearly in azimuth), with
    ``u = clip((e_l - eta)/delta, -1, 1)`` and ``e_l`` the light elevation:

    .. math:: V = \\frac{1}{2} + \\frac{u \\sqrt{1 - u^2} + \\arcsin u}{\\pi}

    The indirect term is one bounce off the surrounding surface: the blocked
    part ``1 - V_sky`` of the hemisphere shows surface of mean albedo
    ``rho_bar`` lit by the material's mean direct irradiance
    ``E_bar = mean(max(n . l, 0) V)`` over a view-independent subsample of
    the map (``E_bar = l_z`` for a flat sample), scaled by
    ``s_ind =`` :data:`INDIRECT_SCALE` to keep it a small correction.  A flat
    sample has ``V_sky = 1`` and no indirect light.
    """
    if not isinstance(view, SurfaceView):
        raise TypeError(f"view must be a SurfaceView, got {type(view).__name__}")
    L = _unit(np.atleast_2d(light_dirs), "light_dirs")
    if L.ndim != 2:
        raise ValueError(f"light_dirs must be (n_l, 3), got shape {np.shape(light_dirs)}")
    n_l = L.shape[0]
    H, W = view.shape
    if out is None:
        out = np.empty((n_l, H, W, 3), np.float32)
    elif out.shape != (n_l, H, W, 3) or out.dtype != np.float32:
        raise ValueError(f"out must be float32 of shape {(n_l, H, W, 3)}, got {out.dtype} {out.shape}")

    b = _ShadeScratch.of(view)
    for k in range(n_l):
        lx, ly, lz = (float(c) for c in L[k])
        o = out[k]
        if lz <= 0.0:
            o.fill(0.0)
            continue
        elev, k0, k1, w = _visible_cosine(view, lx, ly, lz, b)

        # diffuse + indirect
        np.multiply(view.albedo_over_pi, b.nlv[..., None], out=o)
        e_bar = _mean_irradiance(view, L[k], elev, k0, k1, w)
        if e_bar > 0.0:
            np.multiply(view.indirect, np.float32(e_bar), out=b.buf3)  # eq. one-bounce term
            o += b.buf3

        if view.has_specular:
            _add_specular(view, lx, ly, lz, b, o)
    return out


@dataclass(frozen=True, eq=False)
class _ShadeScratch:
    """Buffers of :func:`shade`, reused for every light, and the light-independent GGX terms of a view."""

    nl: np.ndarray  # (H, W) float32: max(n . l, 0)
    nlv: np.ndarray  # (H, W) float32: max(n . l, 0) V
    vis: np.ndarray  # (H, W) float32
    t1: np.ndarray  # (H, W) float32
    t2: np.ndarray  # (H, W) float32
    buf3: np.ndarray  # (H, W, 3) float32
    a2m1: np.ndarray  # alpha^2 - 1
    one_m_a2: np.ndarray  # 1 - alpha^2
    a2_pi: np.ndarray  # alpha^2 / pi
    f0: np.ndarray  # (3,) float64

    @staticmethod
    def of(view: SurfaceView) -> _ShadeScratch:
        """Fresh buffers for ``view``'s texel grid."""
        H, W = view.shape
        a2 = view.alpha2
        a2m1 = a2 - np.float32(1.0)
        one_m_a2 = np.float32(1.0) - a2
        a2_pi = a2 / np.float32(np.pi)
        f0 = view.f0.astype(np.float64)
        return _ShadeScratch(*(np.empty((H, W), np.float32) for _ in range(5)), np.empty((H, W, 3), np.float32),
                             a2m1=a2m1, one_m_a2=one_m_a2, a2_pi=a2_pi, f0=f0)


def _visible_cosine(view: SurfaceView, lx: float, ly: float, lz: float,
                    b: _ShadeScratch) -> tuple[float, int, int, float]:
    """Writes ``max(n . l, 0)`` to ``b.nl`` and that times the LED's visibility ``V`` to ``b.nlv`` for a light
    above the plane; returns its elevation, the horizon slices ``k0``, ``k1`` around its azimuth and the
    weight of ``k1``."""
    nx, ny, nz = view.normal
    hz_all = view.horizon
    n_az = hz_all.shape[0]
    dphi = 2.0 * math.pi / n_az
    delta = view.light_radius
    nl, nlv, vis, t1, t2 = b.nl, b.nlv, b.vis, b.t1, b.t2
    # n . l at the local normal
    np.multiply(nx, np.float32(lx), out=nl)
    np.multiply(ny, np.float32(ly), out=t1)
    nl += t1
    np.multiply(nz, np.float32(lz), out=t1)
    nl += t1
    np.maximum(nl, 0.0, out=nl)

    # cast-shadow visibility from the horizon map, soft LED edge
    elev = math.asin(min(lz, 1.0))
    pos = (math.atan2(ly, lx) % (2.0 * math.pi)) / dphi
    k0 = int(math.floor(pos)) % n_az
    k1 = (k0 + 1) % n_az
    w = pos - math.floor(pos)
    if elev - delta >= max(view.horizon_max[k0], view.horizon_max[k1]):
        np.copyto(nlv, nl)  # light above every horizon: V = 1
    else:
        np.multiply(hz_all[k0], np.float32(1.0 - w), out=t1)
        np.multiply(hz_all[k1], np.float32(w), out=t2)
        t1 += t2  # horizon, linear in azimuth
        np.subtract(np.float32(elev), t1, out=t1)
        t1 *= np.float32(1.0 / delta)
        np.clip(t1, -1.0, 1.0, out=t1)  # u
        np.multiply(t1, t1, out=t2)
        np.subtract(np.float32(1.0), t2, out=t2)
        np.maximum(t2, 0.0, out=t2)
        np.sqrt(t2, out=t2)
        t2 *= t1
        np.arcsin(t1, out=vis)
        vis += t2
        vis *= np.float32(1.0 / math.pi)
        vis += np.float32(0.5)  # eq. disc fraction above the horizon
        np.multiply(nl, vis, out=nlv)
    return elev, k0, k1, w


def _add_specular(view: SurfaceView, lx: float, ly: float, lz: float, b: _ShadeScratch, o: np.ndarray) -> None:
    """Adds the GGX term ``k_s D F / (Lambda_l Lambda_v) max(n . l, 0) V`` of one light to ``o`` (H, W, 3),
    from ``b.nl`` and ``b.nlv`` (:func:`_visible_cosine`)."""
    nx, ny, nz = view.normal
    v, f0, a2 = view.view_dir, b.f0, view.alpha2
    nl, nlv, t1, t2, buf3 = b.nl, b.nlv, b.t1, b.t2, b.buf3
    hv = np.array([lx, ly, lz]) + v
    hv /= np.linalg.norm(hv)
    vh = max(float(hv @ v), 0.0)
    F = (f0 + (1.0 - f0) * (1.0 - vh) ** 5).astype(np.float32)  # eq. Schlick
    # D
    np.multiply(nx, np.float32(hv[0]), out=t1)
    np.multiply(ny, np.float32(hv[1]), out=t2)
    t1 += t2
    np.multiply(nz, np.float32(hv[2]), out=t2)
    t1 += t2
    np.clip(t1, 0.0, 1.0, out=t1)  # n . h
    np.multiply(t1, t1, out=t1)
    t1 *= b.a2m1
    t1 += np.float32(1.0)
    np.multiply(t1, t1, out=t1)
    np.divide(b.a2_pi, t1, out=t1)  # eq. D (Trowbridge-Reitz)
    # Lambda_l
    np.multiply(nl, nl, out=t2)
    t2 *= b.one_m_a2
    t2 += a2
    np.sqrt(t2, out=t2)
    t2 += nl  # eq. Lambda_l
    np.divide(t1, t2, out=t1)
    t1 *= view.spec_scale
    t1 *= nlv
    np.multiply(t1[..., None], F, out=buf3)
    o += buf3


def render_view(
    maps: MaterialMaps,
    view_dir: np.ndarray,
    light_dirs: np.ndarray,
    horizon: np.ndarray | None = None,
    **kwargs,
) -> np.ndarray:
    """BTF of one view for a set of lights: ``shade(prepare_view(...), ...)``.

    Parameters
    ----------
    maps : MaterialMaps
    view_dir : (3,) array_like
    light_dirs : (n_l, 3) array_like
    horizon : (n_az, H, W) ndarray, optional
    **kwargs
        Passed to :func:`prepare_view`.

    Returns
    -------
    btf : (n_l, H, W, 3) ndarray of float32
    """
    return shade(prepare_view(maps, view_dir, horizon, **kwargs), light_dirs)


def downsample2(btf: np.ndarray) -> np.ndarray:
    """Exact 2x2 box (area) mean over the two axes before the channel axis.

    Parameters
    ----------
    btf : (..., 2H, 2W, C) ndarray

    Returns
    -------
    small : (..., H, W, C) ndarray
        Same float dtype (float32 stays float32).
    """
    a = np.asarray(btf)
    if a.ndim < 3:
        raise ValueError(f"btf must be (..., 2H, 2W, C), got shape {a.shape}")
    if a.shape[-3] % 2 or a.shape[-2] % 2:
        raise ValueError(f"rows and columns must be even, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float64)
    s = (a[..., 0::2, 0::2, :] + a[..., 0::2, 1::2, :]) + (a[..., 1::2, 0::2, :] + a[..., 1::2, 1::2, :])
    s *= a.dtype.type(0.25)  # eq. mean of the 2x2 block
    return s
