"""Tests of btfcore.simulate.render (ground-truth BTF renderer)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from btfcore.simulate.materials import MaterialMaps, flat_material, make_material, white_standard
from btfcore.simulate.render import (
    LED_ANGULAR_RADIUS_DEG,
    SurfaceView,
    downsample2,
    horizon_map,
    prepare_view,
    render_view,
    shade,
)

# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------


def _dir(elev_deg: float, az_deg: float) -> np.ndarray:
    e, a = math.radians(elev_deg), math.radians(az_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def _dome(n: int, min_elev_deg: float = 5.0, offset: float = 0.0) -> np.ndarray:
    """Fibonacci directions on the hemisphere above ``min_elev_deg``."""
    k = np.arange(n) + 0.5
    zmin = math.sin(math.radians(min_elev_deg))
    z = zmin + (1.0 - zmin) * k / n
    phi = (k * math.pi * (3.0 - math.sqrt(5.0)) + offset) % (2 * math.pi)
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _maps(height: np.ndarray, albedo: np.ndarray | float = 0.5, specular: float = 0.0) -> MaterialMaps:
    H, W = height.shape
    alb = np.broadcast_to(np.asarray(albedo, np.float32), (H, W, 3)).copy() if np.ndim(albedo) < 3 else albedo
    return MaterialMaps(
        class_name="test",
        height=height.astype(np.float32),
        albedo=alb.astype(np.float32),
        roughness=np.full((H, W), 0.3, np.float32),
        specular=np.full((H, W), specular, np.float32),
        f0=np.full(3, 0.04, np.float32),
        params={},
    )


def _luminance(btf: np.ndarray) -> np.ndarray:
    return btf @ np.array([0.2126, 0.7152, 0.0722], np.float32)




# wall: flat ground with a wall of height HW over columns [C0, C1) spanning all rows
N, C0, C1, HW = 64, 36, 40, 8.0


@pytest.fixture(scope="module")
def wall():
    h = np.zeros((N, N), np.float32)
    h[:, C0:C1] = HW
    maps = _maps(h, albedo=0.5)
    return maps, horizon_map(maps.height)


# ---------------------------------------------------------------------------
# radiometry
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("albedo", [(1.0, 1.0, 1.0), (0.99, 0.99, 0.99), (0.8, 0.3, 0.05)])
def test_flat_lambertian_is_albedo_over_pi_cos(albedo):
    maps = flat_material((8, 8), albedo=albedo, specular=0.0)
    lights = _dome(60, min_elev_deg=2.0)
    for view_dir in _dome(7, min_elev_deg=3.0, offset=0.3):
        btf = render_view(maps, view_dir, lights)
        want = np.asarray(albedo)[None, :] / np.pi * lights[:, 2:3]  # a / pi * cos(theta_i)
        got = btf.reshape(len(lights), -1, 3)
        np.testing.assert_allclose(got, np.broadcast_to(want[:, None, :], got.shape), rtol=1e-5, atol=0)


def test_white_standard_and_lights_below_horizon():
    maps = white_standard((6, 6))
    lights = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.3, 0.2, -0.5]])
    btf = render_view(maps, [0.2, -0.1, 0.9], lights)
    np.testing.assert_allclose(btf[0], 0.99 / np.pi, rtol=1e-6)
    assert np.all(btf[1:] == 0.0)


def _ggx_reference(l, v, alpha, f0):
    """Textbook GGX: D F G / (4 n.l n.v) * n.l at n = z (float64)."""
    n = np.array([0.0, 0.0, 1.0])
    h = (l + v) / np.linalg.norm(l + v)
    nl, nv, nh, vh = l @ n, v @ n, h @ n, v @ h
    a2 = alpha * alpha
    D = a2 / (np.pi * (nh * nh * (a2 - 1) + 1) ** 2)

    def g1(c):
        return 2 * c / (c + np.sqrt(a2 + (1 - a2) * c * c))

    F = f0 + (1 - f0) * (1 - vh) ** 5
    return D * F * g1(nl) * g1(nv) / (4 * nl * nv) * nl


def test_ggx_specular_matches_textbook_formula():
    f0 = np.array([0.9, 0.6, 0.3])
    lights = _dome(40, min_elev_deg=4.0)
    for alpha in (0.05, 0.2, 0.7):
        maps = flat_material((4, 4), albedo=(0, 0, 0), roughness=alpha, specular=1.0, f0=f0)
        for v in _dome(5, min_elev_deg=4.0, offset=1.0):
            btf = render_view(maps, v, lights)
            want = np.array([_ggx_reference(l, v, alpha, f0) for l in lights])
            np.testing.assert_allclose(btf[:, 2, 1, :], want, rtol=2e-4)


def test_specular_peak_in_mirror_direction():
    maps = flat_material((4, 4), albedo=(0.1, 0.1, 0.1), roughness=0.1, specular=1.0)
    view = _dir(40.0, 30.0)
    lights = np.array([_dir(e, a) for e in range(10, 90, 5) for a in range(0, 360, 15)])
    lum = _luminance(render_view(maps, view, lights))[:, 0, 0]
    best = lights[np.argmax(lum)]
    np.testing.assert_allclose(best, _dir(40.0, 210.0), atol=1e-9)  # mirror of the view
    assert lum.max() / np.median(lum) > 20  # a sharp lobe over a dim diffuse floor


# ---------------------------------------------------------------------------
# horizon map and cast shadows
# ---------------------------------------------------------------------------


def test_horizon_map_of_a_wall(wall):
    maps, hz = wall
    assert hz.shape == (32, N, N) and hz.dtype == np.float32
    row = N // 2
    # azimuth 0 looks toward +x (increasing column): the wall's left face
    for k, phi in ((0, 0.0), (2, 2 * math.pi * 2 / 32)):
        for j in range(C0 - 20, C0 - 2):
            d = C0 - j  # perpendicular distance to the wall's first column centre
            want = math.atan(HW * math.cos(phi) / d)
            assert hz[k, row, j] == pytest.approx(want, abs=0.02 + 0.6 * HW / d**2), (k, j)
    # azimuth pi looks toward -x: the wall's right face, distance to column C1 - 1
    for j in range(C1 + 2, C1 + 20):
        assert hz[16, row, j] == pytest.approx(math.atan(HW / (j - (C1 - 1))), abs=1e-6)
    # looking toward -x from the left of the wall: the mirror image of the
    # wall's first column (col C0 -> col -1 - C0) within the search radius N
    for j in range(2, 20):
        assert hz[16, row, j] == pytest.approx(math.atan(HW / (j + 1 + C0)), abs=1e-6)
    assert np.all(hz[16, :, C0 - 8 : C0] == 0.0)  # the image is beyond the search radius N
    # a flat map has no horizon; a larger search radius only raises horizons
    assert np.all(horizon_map(np.zeros((8, 8))) == 0)
    hz_short = horizon_map(maps.height, max_distance=10)
    assert np.all(hz_short <= hz + 1e-7)


def test_horizon_and_parallax_on_a_non_square_grid():
    """Rows of a (32, 64) map are 2 column pitches apart (heights in column pitches)."""
    h = np.zeros((32, 64), np.float32)
    h[8:12, :] = 6.0  # a wall along x; row 11 is its -y face
    hz = horizon_map(h, n_azimuth=32)
    for i in range(13, 24):
        dist = 2.0 * (i - 11)  # looking +y (azimuth 90 deg, slice 8) toward decreasing rows
        assert hz[8, i, 5] == pytest.approx(math.atan(6.0 / dist), abs=1e-6)
    maps = _maps(h)
    z_ref = float(h.mean())
    e = math.radians(45.0)
    view = prepare_view(maps, [0.0, -math.cos(e), math.sin(e)], hz)  # camera toward -y
    # ground texels far from the wall see ground shifted toward +y (lower row)
    # by z_ref / tan(e) pitches = z_ref / 2 rows
    i = 28
    assert view.hit_row[i, 7] == pytest.approx(i - z_ref / 2.0, abs=1e-3)
    assert view.hit_col[i, 7] == pytest.approx(7.0, abs=1e-9)
    flat = render_view(flat_material((6, 10), albedo=(0.3, 0.3, 0.3)), [0.3, 0.1, 0.9], _dome(5))
    np.testing.assert_allclose(flat, 0.3 / np.pi * _dome(5)[:, 2, None, None, None] * np.ones_like(flat), rtol=1e-5)


@pytest.mark.parametrize("elev_deg", [25.0, 40.0])
@pytest.mark.parametrize("az_deg", [0.0, 20.0, 180.0])
def test_cast_shadow_length_of_a_wall(wall, elev_deg, az_deg):
    """Ground is dark exactly within h cos(phi) / tan(elevation) of the wall."""
    maps, hz = wall
    light = _dir(elev_deg, az_deg)
    btf = render_view(maps, [0.0, 0.0, 1.0], light[None], hz)[0]
    lum = _luminance(btf)[N // 2]
    direct = 0.5 / np.pi * light[2]  # lit ground: albedo / pi * cos(theta_i)
    phi = math.radians(az_deg)
    length = HW * abs(math.cos(phi)) / math.tan(math.radians(elev_deg))
    if math.cos(phi) > 0:  # light on the +x side, shadow toward -x of the left face
        dist = {j: C0 - j for j in range(2, C0 - 2)}
    else:
        dist = {j: j - (C1 - 1) for j in range(C1 + 2, N - 2)}
    # penumbra: the LED disc (and the wall edge) spread the boundary
    spread = 1.0 + HW * math.radians(LED_ANGULAR_RADIUS_DEG) / math.sin(math.radians(elev_deg)) ** 2
    n_dark = n_lit = 0
    for j, d in dist.items():
        if d < length - spread:
            assert 0.0 < lum[j] < 0.4 * direct, (j, d, length)  # shadow, lit only by the indirect term
            n_dark += 1
        elif d > length + spread:
            assert lum[j] >= direct * (1 - 1e-5), (j, d, length)  # fully lit (plus indirect)
            assert lum[j] <= direct * 1.25
            n_lit += 1
    assert n_dark >= 3 and n_lit >= 3


def test_shadow_edge_is_soft_and_monotonic(wall):
    maps, hz = wall
    row, j = N // 2, C0 - 10  # a ground texel 10 columns from the wall
    eta = math.atan(HW / 10)  # its horizon toward +x
    delta = math.radians(LED_ANGULAR_RADIUS_DEG)
    elevs = np.degrees(eta + np.linspace(-2.0, 2.0, 41) * delta)
    lights = np.array([_dir(e, 0.0) for e in elevs])
    view = prepare_view(maps, [0, 0, 1], hz)
    lum = _luminance(shade(view, lights))[:, row, j] / (0.5 / np.pi * lights[:, 2])
    assert lum[0] < 0.2 and lum[-1] >= 1.0 - 1e-5
    assert np.all(np.diff(lum) >= -1e-4)  # monotonic
    mid = lum[20]  # light centre exactly on the horizon: half the disc is visible
    assert mid == pytest.approx(0.5 * (lum[0] + lum[-1]), abs=0.1)
    assert np.count_nonzero((lum > lum[0] + 0.05) & (lum < lum[-1] - 0.05)) >= 5  # not a hard step


def test_indirect_term_is_small_and_positive(wall):
    maps, hz = wall
    view = prepare_view(maps, [0, 0, 1], hz)
    occ = view.occlusion[N // 2]

    def blocked(d):  # cosine-weighted fraction hidden by an infinite wall at distance d
        return 0.5 * (1 - math.cos(math.atan(HW / d))) if d <= N else 0.0

    # ground left of the wall sees the wall and (mirror boundary) its image
    for j in (2, 12, 24, 30, 33):
        want = blocked(C0 - j) + blocked(j + 1 + C0)
        assert occ[j] == pytest.approx(want, rel=0.15, abs=0.005), j
    assert occ[C0 - 3] > 5 * occ[2]
    assert view.occlusion.max() <= 0.6
    # the indirect light in a shadow is a small fraction of the direct light
    light = _dir(20.0, 0.0)
    lum = _luminance(shade(view, light[None]))[0, N // 2]
    direct = 0.5 / np.pi * light[2]
    shadowed = lum[C0 - 15 : C0 - 2]  # within the shadow length 8 / tan(20 deg) = 22
    assert np.all(shadowed > 0.0) and np.all(shadowed < 0.1 * direct)


# ---------------------------------------------------------------------------
# parallax and masking
# ---------------------------------------------------------------------------

P0, P1, HP = 24, 40, 6.0  # plateau columns [P0, P1), height HP


@pytest.fixture(scope="module")
def plateau():
    h = np.zeros((N, N), np.float32)
    h[:, P0:P1] = HP
    albedo = np.zeros((N, N, 3), np.float32)
    albedo[..., 1] = 0.8  # green ground
    albedo[:, P0:P1] = (0.8, 0.0, 0.0)  # red plateau
    maps = _maps(h, albedo=albedo)
    return maps, horizon_map(maps.height)


@pytest.mark.parametrize("elev_deg", [30.0, 55.0])
def test_parallax_shift_of_seen_points(plateau, elev_deg):
    maps, hz = plateau
    z_ref = HP * (P1 - P0) / N  # reference plane = mean height
    t = 1.0 / math.tan(math.radians(elev_deg))
    view = prepare_view(maps, _dir(elev_deg, 0.0), hz)
    assert isinstance(view, SurfaceView)
    assert view.z_ref == pytest.approx(z_ref)
    r = N // 2
    # texels that see the plateau top: shifted toward the camera (+x)
    for j in range(P0 + 1, P1 - 1 - math.ceil((HP - z_ref) * t)):
        assert view.hit_col[r, j] == pytest.approx(j + (HP - z_ref) * t, abs=1e-3)
        assert view.hit_height[r, j] == pytest.approx(HP, abs=1e-3)
    # texels that see the ground in front of it: shifted away from the camera
    for j in range(P1 + 2 + math.ceil(z_ref * t), N - 4):
        assert view.hit_col[r, j] == pytest.approx(j - z_ref * t, abs=1e-3)
        assert view.hit_height[r, j] == pytest.approx(0.0, abs=1e-3)
    np.testing.assert_array_equal(view.hit_row, np.broadcast_to(np.arange(N)[:, None], (N, N)))


def test_masking_hides_ground_behind_the_plateau(plateau):
    maps, hz = plateau
    elev = 30.0
    hidden = (P0 - 1 - HP / math.tan(math.radians(elev)) + 1.0, P0 - 1.5)  # ground behind the step
    oblique = prepare_view(maps, _dir(elev, 0.0), hz)
    top = prepare_view(maps, [0, 0, 1], hz)
    for v, n_expected in ((oblique, 0), (top, None)):
        ground = v.hit_height < 0.05
        in_zone = ground & (v.hit_col > hidden[0]) & (v.hit_col < hidden[1])
        if n_expected == 0:
            assert not in_zone.any()
        else:
            assert in_zone.sum() >= N * 5  # seen from above


def test_rendered_plateau_edges_move_with_view(plateau):
    maps, hz = plateau
    z_ref = HP * (P1 - P0) / N
    for elev in (30.0, 60.0):
        t = 1.0 / math.tan(math.radians(elev))
        v = _dir(elev, 0.0)
        img = render_view(maps, v, v[None], hz)[0, N // 2]  # lit from the camera
        red = img[:, 0] / np.maximum(img[:, 0] + img[:, 1], 1e-12)
        is_red = np.flatnonzero(red > 0.5)
        left, right = is_red[0], is_red[-1]
        # top starts where the ray meets height HP at column P0; the lit
        # step face (bilinear ramp P1-1 -> P1) turns green half-way down
        want_left = P0 - (HP - z_ref) * t
        want_right = (P1 - 0.5) - (HP / 2 - z_ref) * t
        assert abs(left - want_left) <= 1.0, (elev, left, want_left)
        assert abs(right - want_right) <= 1.0, (elev, right, want_right)


# ---------------------------------------------------------------------------
# materials: robustness, dynamic range, determinism, resolution
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("class_name", ["leather", "cloth", "wood", "metal", "stone", "carpet"])
def test_no_negative_or_nan_at_grazing_angles(class_name, sources):
    maps = make_material(class_name, 11, (24, 24), sources)
    lights = np.concatenate([_dome(20, 0.05), [[1, 0, 1e-4], [0, 1, 0], [0, 0, 1]]])
    for v in ([1.0, 0.0, 2e-3], [0.0, -1.0, 0.02], [0.3, 0.3, 1.0]):
        btf = render_view(maps, v, lights)
        assert np.all(np.isfinite(btf)) and btf.min() >= 0.0


def _dynamic_range(maps: MaterialMaps) -> tuple[float, float]:
    hz = horizon_map(maps.height)
    lights = _dome(48, min_elev_deg=8.0)
    lum = np.concatenate([_luminance(render_view(maps, v, lights, hz)).ravel()
                          for v in _dome(8, min_elev_deg=10.0, offset=0.7)])
    lo, hi = np.percentile(lum, [0.1, 99.9])
    return float(lo), float(hi)


@pytest.mark.parametrize("class_name", ["metal", "stone"])
def test_dynamic_range_over_dome(class_name, sources):
    for seed in (0, 1, 2):
        lo, hi = _dynamic_range(make_material(class_name, seed, (48, 48), sources))
        assert lo > 0.0  # shadows are not black: the indirect term
        assert hi / lo >= 1e3, (class_name, seed, hi / lo)


def test_render_is_deterministic_and_out_buffer(sources):
    maps = make_material("stone", 3, (32, 32), sources)
    lights = _dome(12)
    a = render_view(maps, [0.3, -0.4, 0.7], lights)
    b = render_view(make_material("stone", 3, (32, 32), sources), [0.3, -0.4, 0.7], lights)
    assert np.array_equal(a, b)
    view = prepare_view(maps, [0.3, -0.4, 0.7])
    buf = np.full((12, 32, 32, 3), np.nan, np.float32)
    res = shade(view, lights, out=buf)
    assert res is buf and np.array_equal(buf, a)
    # shading one light at a time gives the same bits as a batch
    single = np.stack([shade(view, lights[i : i + 1])[0] for i in range(12)])
    assert np.array_equal(single, a)
    with pytest.raises(ValueError, match="out"):
        shade(view, lights, out=np.empty((12, 32, 32, 3), np.float64))


def test_twice_resolution_downsampled_matches(sources):
    """A 2x render box-filtered to 1x agrees with a 1x render on average."""
    lights = _dome(10, min_elev_deg=20.0)
    for c in ("stone", "leather"):
        lo = make_material(c, 2, (32, 32), sources)
        hi = make_material(c, 2, (64, 64), sources)
        v = _dir(50.0, 70.0)
        b_lo = render_view(lo, v, lights)
        b_hi = downsample2(render_view(hi, v, lights))
        assert b_hi.shape == b_lo.shape
        mean_lo = b_lo.mean(axis=(1, 2, 3))
        mean_hi = b_hi.mean(axis=(1, 2, 3))
        np.testing.assert_allclose(mean_hi, mean_lo, rtol=0.08)
        corr = np.corrcoef(_luminance(b_lo).ravel(), _luminance(b_hi).ravel())[0, 1]
        assert corr > 0.8, (c, corr)


def test_input_validation():
    maps = flat_material((4, 4))
    with pytest.raises(ValueError, match="above the sample"):
        prepare_view(maps, [0.0, 1.0, -0.1])
    with pytest.raises(ValueError, match="NaN"):
        prepare_view(maps, [np.nan, 0.0, 1.0])
    with pytest.raises(ValueError, match="horizon"):
        prepare_view(maps, [0, 0, 1], horizon=np.zeros((32, 5, 4), np.float32))
    view = prepare_view(maps, [0, 0, 1])
    with pytest.raises(ValueError, match="zero-length"):
        shade(view, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="height"):
        horizon_map(np.zeros(5))


# ---------------------------------------------------------------------------
# downsample2
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_downsample2_is_2x2_block_mean(dtype):
    rng = np.random.default_rng(5)
    a = rng.random((3, 2, 8, 10, 3)).astype(dtype)
    small = downsample2(a)
    assert small.shape == (3, 2, 4, 5, 3) and small.dtype == dtype
    want = a.astype(np.float64).reshape(3, 2, 4, 2, 5, 2, 3).mean(axis=(3, 5))
    np.testing.assert_allclose(small, want, rtol=1e-6 if dtype == np.float32 else 1e-14)
    assert small[1, 0, 2, 3, 1] == pytest.approx(a[1, 0, 4:6, 6:8, 1].mean(), rel=1e-6)
    with pytest.raises(ValueError, match="even"):
        downsample2(a[..., :7, :, :])
