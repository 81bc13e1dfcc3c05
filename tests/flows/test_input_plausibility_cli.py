"""Issue 13 on the command line: a material given as `--white` and a `--class` that is not one of the model's
are refused (exit EXIT_BAD_INPUT) before anything is written."""

from __future__ import annotations

import numpy as np
import zarr

from flows.cli import EXIT_BAD_INPUT


def _model_from(btf_path, model_dir, k: int = 4) -> None:
    """A model store whose `leather` basis is the truncated SVD of a BTF store (same sampling)."""
    src = zarr.open_group(str(btf_path), mode="r")
    B = np.asarray(src["btf"][...], dtype=np.float64)
    U, s, _ = np.linalg.svd(B.reshape(B.shape[0], -1), full_matrices=False)
    group = zarr.open_group(str(model_dir / "model.zarr"), mode="w", zarr_format=3)
    for name in ("light_dir", "view_dir"):
        group.create_array(name, data=src[name][...])
    group.attrs.put({"schema": "btf-model", "schema_version": "1.0", "rows_id": "test", "n_lv": int(B.shape[0])})
    sub = group.require_group("classes/leather/als")
    sub.create_array("U", data=U[:, :k])
    sub.create_array("sigma", data=s[:k])
    sub.attrs.put({"method": "test", "key": "svd"})


def test_a_material_as_white_standard_and_a_path_as_class_are_refused(run_btf, tiny_btf, tmp_path):
    _model_from(tiny_btf, tmp_path / "model")
    out = tmp_path / "rec.zarr"
    code, _, err = run_btf("reconstruct", tiny_btf, "--model", tmp_path / "model", "--class", "../../etc",
                           "--out", out)
    assert code == EXIT_BAD_INPUT, err
    assert "--class '../../etc' is a path, not a class name; choose one of: leather" in err, err
    code, _, err = run_btf("reconstruct", tiny_btf, "--model", tmp_path / "model", "--class", "leather",
                           "--white", tiny_btf, "--out", out)
    assert code == EXIT_BAD_INPUT, err
    assert f"{tiny_btf}: not a white standard: brightness_spread" in err, err
    assert not out.exists() and not (tmp_path / "rec.partial.zarr").exists()

    capture = next(tiny_btf.parent.glob("*-leather.zarr"))
    code, _, err = run_btf("ingest", capture, "--white", tiny_btf, "--out", tmp_path / "cal.zarr")
    assert code == EXIT_BAD_INPUT, err
    assert f"{tiny_btf}: not a white standard" in err and "white-standard capture" in err, err
    assert not (tmp_path / "cal.zarr").exists() and not (tmp_path / "cal.partial.zarr").exists()
