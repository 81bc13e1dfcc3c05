"""Device presets: counts, geometry conventions, homographies against full pinhole projection."""

from __future__ import annotations

import json

import numpy as np
import pytest

from btfcore.dome import (
    DEVICE_NAMES,
    UBO_DOME1_RINGS,
    Device,
    SensorSpec,
    get_device,
)


@pytest.fixture(scope="module", params=DEVICE_NAMES)
def device(request):
    return get_device(request.param)


def _theta_phi(v):
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return np.rad2deg(np.arccos(np.clip(v[..., 2], -1, 1))), np.rad2deg(np.arctan2(v[..., 1], v[..., 0])) % 360


def _corners(s):
    h = s / 2
    return np.array([[-h, -h], [h, -h], [h, h], [-h, h]])


def test_counts():
    tiny, bonn, ubo = (get_device(n) for n in DEVICE_NAMES)
    assert (tiny.n_turn, tiny.n_cam, tiny.n_leds) == (3, 4, 16)
    assert (bonn.n_turn, bonn.n_cam, bonn.n_leds) == (12, 11, 198)
    assert bonn.n_lv == 26_136
    assert (ubo.n_turn, ubo.n_cam, ubo.n_leds) == (1, 151, 151)
    assert ubo.n_lv == 151 * 151
    assert tiny.texture_shape == (32, 32) and bonn.texture_shape == (128, 128) and ubo.texture_shape == (128, 128)
    assert tiny.sensor.n_exposures == 3 and bonn.sensor.n_exposures == 4
    np.testing.assert_allclose(bonn.turntable_angle_deg, np.arange(12) * 30.0)
    np.testing.assert_allclose(tiny.turntable_angle_deg, [0, 120, 240])


def test_unknown_device_lists_valid_names():
    with pytest.raises(ValueError, match="tiny, bonn-dome2, ubo-dome1"):
        get_device("dome-x")


def test_bonn_dome2_geometry():
    d = get_device("bonn-dome2")
    cam_t, cam_p = _theta_phi(d.camera_position)
    np.testing.assert_allclose(cam_t, np.arange(11) * 7.5, atol=1e-9)
    assert np.allclose(d.camera_position[:, 1], 0) and (d.camera_position[:, 0] >= -1e-12).all()
    np.testing.assert_allclose(np.linalg.norm(d.camera_position, axis=1), 0.65)
    # the 10 lowest cameras (theta > 0) each have an LED exactly opposite (phi + 180 deg): mirror direction
    cams = d.camera_position / np.linalg.norm(d.camera_position, axis=1, keepdims=True)
    leds = d.led_position / np.linalg.norm(d.led_position, axis=1, keepdims=True)
    mirror = cams * np.array([-1.0, -1.0, 1.0])
    dist = np.rad2deg(np.arccos(np.clip(mirror @ leds.T, -1, 1)))          # (n_cam, n_leds)
    nearest = dist[1:].argmin(axis=1)
    np.testing.assert_allclose(leds[nearest], mirror[1:], atol=1e-12)
    assert len(set(dist[1:].argmin(axis=1))) == 10
    # the other 188 avoid the cameras and each other, and cover the hemisphere
    others = np.setdiff1d(np.arange(198), dist[1:].argmin(axis=1))
    assert len(others) == 188
    ang_cam = np.rad2deg(np.arccos(np.clip(leds[others] @ cams.T, -1, 1)))
    assert ang_cam.min() > 3.0
    ang_led = np.rad2deg(np.arccos(np.clip(leds @ leds.T, -1, 1))) + 360 * np.eye(198)
    assert ang_led.min() > 3.0
    led_t, _ = _theta_phi(d.led_position)
    assert led_t.min() < 5 and led_t.max() > 85
    # frontal camera: the sample spans ~200 px
    H = d.homography(0, 0)
    q = H @ np.array([[-0.025, 0.025], [0, 0], [1, 1]])
    q = q[:2] / q[2]
    assert abs(np.linalg.norm(q[:, 1] - q[:, 0]) - 200) < 1e-6


def test_ubo_dome1_rings_and_flashes():
    d = get_device("ubo-dome1")
    assert d.lights_are_flashes
    np.testing.assert_array_equal(d.led_position, d.camera_position)
    np.testing.assert_allclose(d.turntable_angle_deg, [0.0])
    th, ph = _theta_phi(d.camera_position)
    start = 0
    for theta, count, offset in UBO_DOME1_RINGS:
        sl = slice(start, start + count)
        np.testing.assert_allclose(th[sl], theta, atol=1e-9)
        expected = (offset + 360.0 * np.arange(count) / count) % 360
        if theta > 0:  # azimuth undefined at the zenith
            diff = (ph[sl] - expected + 180) % 360 - 180
            np.testing.assert_allclose(diff, 0, atol=1e-7)
        start += count
    assert start == 151
    assert [c for _, c, _ in UBO_DOME1_RINGS] == [1, 6, 12, 12, 12, 18, 18, 24, 24, 24]
    assert [o for _, _, o in UBO_DOME1_RINGS] == [0, 15, 0, 15, 0, 0, 7.5, 0, 7.5, 0]
    assert [t for t, _, _ in UBO_DOME1_RINGS] == [0, 11, 23.5, 30, 37.5, 45, 52.5, 60, 67.5, 75]


def test_tiny_has_specular_configurations():
    d = get_device("tiny")
    th, ph = _theta_phi(d.camera_position)
    np.testing.assert_allclose(th, [0, 25, 50, 75], atol=1e-9)
    cams = d.camera_position / np.linalg.norm(d.camera_position, axis=1, keepdims=True)
    for t in range(d.n_turn):
        L = d.light_dirs(t)
        hits = 0
        for c in range(d.n_cam):
            v = d.view_dir(t, c)
            mirror = np.array([-v[0], -v[1], v[2]])
            hits += np.isclose(L @ mirror, 1.0, atol=1e-9).any()
        assert hits >= 3     # mirror reflection into the 25, 50 and 75 deg cameras at every position
    # no LED coincides with a camera
    leds = d.led_position / np.linalg.norm(d.led_position, axis=1, keepdims=True)
    assert np.rad2deg(np.arccos(np.clip(leds @ cams.T, -1, 1))).min() > 5


def test_rotations_are_orthonormal_and_cameras_look_at_the_origin(device):
    R = device.camera_R
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    # camera centre maps to the camera origin; the world origin lies on the optical axis
    np.testing.assert_allclose(np.einsum("cij,cj->ci", R, device.camera_position) + device.camera_t, 0, atol=1e-12)
    axis = device.camera_t / np.linalg.norm(device.camera_t, axis=1, keepdims=True)
    np.testing.assert_allclose(axis, np.tile([0, 0, 1.0], (device.n_cam, 1)), atol=1e-12)
    # the sample centre projects to the ROI centre
    rows, cols = device.roi_shape
    for c in range(0, device.n_cam, max(1, device.n_cam // 7)):
        q = device.homography(0, c) @ np.array([0, 0, 1.0])
        np.testing.assert_allclose(q[:2] / q[2], [(cols - 1) / 2, (rows - 1) / 2], atol=1e-9)


def test_homography_equals_full_pinhole_projection(device):
    s = device.sample_size_m
    corners = _corners(s)
    Hs = device.homographies()
    assert Hs.shape == (device.n_turn, device.n_cam, 3, 3)
    for t in range(device.n_turn):
        a = np.deg2rad(device.turntable_angle_deg[t])
        Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        X = np.c_[corners, np.zeros(4)] @ Rz.T                               # sample corners in the world
        for c in range(device.n_cam):
            K, R, tv = device.camera_K[c], device.camera_R[c], device.camera_t[c]
            q = (X @ R.T + tv) @ K.T                                         # K (R X + t)
            ref = q[:, :2] / q[:, 2:]
            h = np.c_[corners, np.ones(4)] @ Hs[t, c].T
            np.testing.assert_allclose(h[:, :2] / h[:, 2:], ref, atol=1e-8)
            np.testing.assert_allclose(Hs[t, c], device.homography(t, c), atol=1e-12)
            # inside the ROI, pixel centres at integers: frame spans [-0.5, size - 0.5]
            rows, cols = device.roi_shape
            assert (ref[:, 0] > -0.5).all() and (ref[:, 0] < cols - 0.5).all()
            assert (ref[:, 1] > -0.5).all() and (ref[:, 1] < rows - 0.5).all()
            assert (q[:, 2] > 0).all()


def test_frontal_size_and_foreshortening():
    for name, px in (("tiny", 48.0), ("bonn-dome2", 200.0)):
        d = get_device(name)
        cams_theta, _ = _theta_phi(d.camera_position)
        for c, theta in enumerate(cams_theta):
            q = np.c_[_corners(d.sample_size_m), np.ones(4)] @ d.homography(0, c).T
            q = q[:, :2] / q[:, 2:]
            width = q[:, 0].max() - q[:, 0].min()
            height = q[:, 1].max() - q[:, 1].min()
            if theta == 0:
                assert abs(width - px) < 1e-6 and abs(height - px) < 1e-6
            # rows are foreshortened by cos(theta) (perspective adds a few per cent)
            ratio = height / width
            assert abs(ratio - np.cos(np.deg2rad(theta))) < 0.03, (name, theta, ratio)
    assert get_device("tiny").roi_shape[0] >= 64 and get_device("bonn-dome2").roi_shape[0] >= 224


def test_directions_are_unit_and_rotate_with_the_turntable(device):
    for t in range(device.n_turn):
        L = device.light_dirs(t)
        np.testing.assert_allclose(np.linalg.norm(L, axis=1), 1.0)
        for c in (0, device.n_cam - 1):
            np.testing.assert_allclose(np.linalg.norm(device.view_dir(t, c)), 1.0)
        # sample frame = world frame rotated by -a: azimuths drop by a, elevation kept
        a = device.turntable_angle_deg[t]
        th0, ph0 = _theta_phi(device.light_dirs(0))
        th, ph = _theta_phi(L)
        np.testing.assert_allclose(th, th0, atol=1e-9)
        off = th0 > 1e-6
        d_phi = (ph[off] - (ph0[off] - a + device.turntable_angle_deg[0]) + 180) % 360 - 180
        np.testing.assert_allclose(d_phi, 0, atol=1e-7)
        v0, v = device.view_dir(0, device.n_cam - 1), device.view_dir(t, device.n_cam - 1)
        np.testing.assert_allclose((np.rad2deg(np.arctan2(v[1], v[0]) - np.arctan2(v0[1], v0[0])) + a + 180) % 360
                                   - 180, 0, atol=1e-7)


def test_directions_world_frame_at_angle_zero():
    d = get_device("tiny")
    np.testing.assert_allclose(d.light_dirs(0), d.led_position / np.linalg.norm(d.led_position, axis=1)[:, None])
    # turntable at 120 deg: a sample-frame direction d_s maps back to the world by Rz(120)
    a = np.deg2rad(120)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    np.testing.assert_allclose(d.light_dirs(1) @ Rz.T, d.light_dirs(0), atol=1e-12)
    np.testing.assert_allclose(Rz @ d.view_dir(1, 3), d.view_dir(0, 3), atol=1e-12)


def test_lv_directions_order():
    d = get_device("tiny")
    L, V, idx = d.lv_directions()
    assert L.shape == V.shape == idx.shape == (d.n_lv, 3) and idx.dtype == np.int32
    lv = (idx[:, 0] * d.n_cam + idx[:, 1]) * d.n_leds + idx[:, 2]
    np.testing.assert_array_equal(lv, np.arange(d.n_lv))
    for row in (0, 17, 100, d.n_lv - 1):
        t, c, l = idx[row]
        np.testing.assert_allclose(L[row], d.light_dirs(t)[l])
        np.testing.assert_allclose(V[row], d.view_dir(t, c))


def test_led_gains_vary_and_are_fixed():
    for name in DEVICE_NAMES:
        g = get_device(name).led_rgb_gain
        assert g.shape == (get_device(name).n_leds, 3)
        assert 0.02 < g.std() < 0.1 and abs(g.mean() - 1) < 0.05
        np.testing.assert_array_equal(g, get_device(name).led_rgb_gain)


def test_overrides_and_json_round_trip():
    d = get_device("tiny", bayer_pattern="GBRG", texture_shape=(16, 16))
    assert d.sensor.bayer_pattern == "GBRG" and d.texture_shape == (16, 16)
    sub = d.with_overrides(turntable_angle_deg=d.turntable_angle_deg[:1])
    assert sub.n_turn == 1 and sub.n_lv == d.n_lv // 3
    np.testing.assert_allclose(sub.homography(0, 2), d.homography(0, 2))
    # a larger ROI keeps the sample centred: homography shifts by the change of centre
    big = d.with_overrides(roi_shape=(100, 90))
    shift = np.array([[1, 0, (90 - d.roi_shape[1]) / 2], [0, 1, (100 - d.roi_shape[0]) / 2], [0, 0, 1]])
    np.testing.assert_allclose(big.homography(1, 3), shift @ d.homography(1, 3), atol=1e-9)
    psf = d.with_overrides(sensor={"psf_sigma_px": 0.8})
    assert psf.sensor.psf_sigma_px == 0.8 and psf.sensor.bayer_pattern == "GBRG"
    cams = d.with_overrides(camera_indices=[0, 3])
    assert cams.n_cam == 2 and cams.n_leds == 16
    np.testing.assert_allclose(cams.homography(2, 1), d.homography(2, 3))
    with pytest.raises(TypeError):
        d.with_overrides(nonsense=1)
    ubo = get_device("ubo-dome1").with_overrides(camera_indices=[0, 5, 9])
    assert ubo.n_cam == ubo.n_leds == 3 and ubo.lights_are_flashes
    blob = json.dumps(d.to_json())
    back = Device.from_json(json.loads(blob))
    for name in ("led_position", "camera_K", "camera_R", "camera_t", "turntable_angle_deg", "led_rgb_gain"):
        np.testing.assert_array_equal(getattr(back, name), getattr(d, name))
    assert back.sensor.to_json() == d.sensor.to_json()
    assert back.roi_shape == d.roi_shape and back.texture_shape == d.texture_shape


def test_device_is_immutable():
    d = get_device("tiny")
    with pytest.raises(ValueError):
        d.led_position[0, 0] = 1.0
    with pytest.raises(AttributeError):
        d.name = "x"


def test_sensor_spec():
    s = SensorSpec()
    assert s.white_level == min(4095, 64 + int(5500 / 1.5)) == 3730
    assert SensorSpec(bit_depth=10, black_level=16).white_level == 1023
    assert SensorSpec.from_json(json.loads(json.dumps(s.to_json()))).to_json() == s.to_json()
    for bad in ({"bayer_pattern": "RGBG"}, {"bit_depth": 17}, {"black_level": 5000}, {"gain_e_per_dn": 0},
                {"sensitivity_rgb": (1.0, -1.0, 1.0)}, {"n_exposures": 0}):
        with pytest.raises(ValueError):
            SensorSpec(**bad)


def test_invalid_device_is_refused():
    d = get_device("tiny")
    with pytest.raises(ValueError, match="not above the sample"):
        d.with_overrides(led_position=d.led_position * np.array([1, 1, -1.0]))
    with pytest.raises(ValueError, match="not a rotation"):
        d.with_overrides(camera_R=d.camera_R * 2)
    with pytest.raises(ValueError, match="NaN"):
        d.with_overrides(camera_t=d.camera_t * np.nan)


@pytest.mark.parametrize("f", [2, 3])
def test_pixel_scale_maps_every_pixel_to_its_block(f):
    """A camera with f times the pixels: a 1x pixel centre x maps to the 2x pixel centre f x + (f - 1) / 2."""
    d = get_device("tiny")
    big = d.with_overrides(pixel_scale=f)
    assert big.roi_shape == (f * d.roi_shape[0], f * d.roi_shape[1])
    assert big.texture_shape == d.texture_shape and big.sensor.to_json() == d.sensor.to_json()
    np.testing.assert_array_equal(big.camera_R, d.camera_R)
    corners = np.c_[_corners(d.sample_size_m), np.ones(4)]
    for t, c in ((0, 0), (1, 3), (2, 2)):
        small_px = corners @ d.homography(t, c).T
        big_px = corners @ big.homography(t, c).T
        np.testing.assert_allclose(big_px[:, :2] / big_px[:, 2:], f * small_px[:, :2] / small_px[:, 2:] + (f - 1) / 2,
                                   atol=1e-9)
        np.testing.assert_allclose(big.homographies()[t, c], big.homography(t, c))
    # the sample centre stays at the ROI centre; other overrides are applied first
    np.testing.assert_allclose(big.camera_K[:, :2, 2], np.broadcast_to((np.array(big.roi_shape[::-1]) - 1) / 2,
                                                                       (big.n_cam, 2)))
    both = d.with_overrides(pixel_scale=f, roi_shape=(80, 76))
    assert both.roi_shape == (80 * f, 76 * f)
    np.testing.assert_allclose(both.camera_K[:, :2, 2], np.broadcast_to((np.array(both.roi_shape[::-1]) - 1) / 2,
                                                                        (both.n_cam, 2)))
    assert d.with_overrides(pixel_scale=1).roi_shape == d.roi_shape
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="pixel_scale"):
            d.with_overrides(pixel_scale=bad)


def test_twice_the_pixels_area_down_sampled_is_the_camera():
    """A 2x camera's frame of a smooth scene, each 2 x 2 block averaged, is the 1x camera's frame."""
    from btfcore.simulate.camera import render_frame

    d = get_device("tiny")
    big = d.with_overrides(pixel_scale=2)
    v, u = np.mgrid[0:64, 0:64] / 63.0
    texture = np.stack([0.2 + 0.5 * u, 0.3 + 0.4 * np.sin(2 * v) * u, 0.6 - 0.3 * v], axis=-1)[None]
    texture = texture.astype(np.float32)
    background = np.full((1, 3), 0.25, dtype=np.float32)          # the holder: a smooth scene everywhere
    for t, c in ((0, 0), (1, 2), (2, 3)):
        small = render_frame(texture, background, d.homography(t, c), d.roi_shape, d.sample_size_m, supersample=6)
        large = render_frame(texture, background, big.homography(t, c), big.roi_shape, big.sample_size_m)
        blocks = large.reshape(1, d.roi_shape[0], 2, d.roi_shape[1], 2, 3).mean(axis=(2, 4))
        # 6 x 6 sub-pixels per 1x pixel either way, at the same points of the sample plane when every
        # 1x pixel is exactly its 2 x 2 block (measured: 1.2e-7, float32 rounding)
        assert np.abs(blocks - small).max() < 1e-5, np.abs(blocks - small).max()
