"""Issue 13: inputs that are readable but wrong are refused with a message that says what to give instead:
a material given as the white standard, a class name that is not one of the model's (or a path)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import zarr

from btfcore.capture.radiometric import WHITE_TOLERANCES
from tasks.radiometric import load_calibration
from tasks.reconstruct import ReconstructSettings, check_inputs


def test_a_leather_btf_is_refused_as_the_white_standard(tiny_btf):
    """`--white LEATHER_BTF` calibrated the LEDs on leather without a word; now the statistics of the white
    store are checked in the pass that measures the gains, before they calibrate anything."""
    with pytest.raises(ValueError) as err:
        load_calibration(tiny_btf)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"{tiny_btf}: not a white standard: ")
    assert re.search(rf"brightness_spread = 0\.\d+ > {WHITE_TOLERANCES['brightness_spread']:g} \(", msg), msg
    assert "give --white the ingest of a white-standard capture" in msg


def _btf_input(path, n_lv=6, h=4, w=4):
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    rng = np.random.default_rng(0)
    group.create_array("btf", data=rng.random((n_lv, h, w, 3)).astype(np.float32))
    dirs = np.tile([0.0, 0.0, 1.0], (n_lv, 1))
    for name in ("light_dir", "view_dir"):
        group.create_array(name, data=dirs)
    group.create_array("lv_index", data=np.stack([np.zeros(n_lv), np.zeros(n_lv), np.arange(n_lv)], 1).astype(np.int32))
    group.attrs.put({"schema": "btf-texture", "complete": True, "turntable_cameras_leds": [1, 1, n_lv],
                     "texture_shape": [h, w], "ingest_hash": "test"})
    return dirs


def _model(path, dirs, classes=("leather", "wood"), k=2):
    group = zarr.open_group(str(path / "model.zarr"), mode="w", zarr_format=3)
    for name in ("light_dir", "view_dir"):
        group.create_array(name, data=dirs)
    group.attrs.put({"schema": "btf-model", "schema_version": "1.0", "rows_id": "test", "n_lv": len(dirs)})
    U = np.linalg.qr(np.random.default_rng(1).standard_normal((len(dirs), k)))[0]
    for cls in classes:
        sub = group.require_group(f"classes/{cls}/als")
        sub.create_array("U", data=U)
        sub.create_array("sigma", data=np.arange(k, 0, -1.0))
        sub.attrs.put({"method": "test", "key": cls})
    (path / "etc").mkdir()                                         # something a path-like class could reach
    return path


@pytest.mark.parametrize("method", ["pinv", "thresholded"])
def test_class_must_be_one_of_the_models_classes(tmp_path, method):
    """`btf reconstruct --class ../../etc` failed inside Zarr without naming the valid classes (and with
    --method thresholded was not checked before the cluster at all)."""
    dirs = _btf_input(tmp_path / "in.zarr")
    model = _model(tmp_path / "model", dirs)
    check_inputs(tmp_path / "in.zarr", model, ReconstructSettings(cls="leather", method=method))
    for cls, kind in (("../../etc", "is a path, not a class name"), ("leather/../wood", "is a path"),
                      ("..", "is a path"), ("stone", "is not a class of this model"), ("", "is not a class")):
        with pytest.raises(ValueError) as err:
            check_inputs(tmp_path / "in.zarr", model, ReconstructSettings(cls=cls, method=method))
        msg = str(err.value)
        assert "\n" not in msg and msg.startswith(f"{model}: --class {cls!r} {kind}"), msg
        assert msg.endswith("choose one of: leather, wood"), msg


def test_basis_must_be_in_the_class(tmp_path):
    """A basis the class lacks is named with the ones it has, also for --method thresholded (whose operator
    is built on the cluster: it was not checked before one started)."""
    dirs = _btf_input(tmp_path / "in.zarr")
    model = _model(tmp_path / "model", dirs)
    zarr.open_group(str(model / "model.zarr"), mode="r+", zarr_format=3).require_group("classes/stone/log_y")
    for cls, settings, missing, has in (
            ("wood", dict(basis="log_y"), "log_y", "als"),
            ("stone", dict(method="thresholded"), "als", "log_y")):
        with pytest.raises(ValueError) as err:
            check_inputs(tmp_path / "in.zarr", model, ReconstructSettings(cls=cls, **settings))
        msg = str(err.value)
        assert "\n" not in msg and msg.startswith(f"{model}: class {cls} has no basis {missing} (it has: {has})"), msg
        assert "--basis" in msg
