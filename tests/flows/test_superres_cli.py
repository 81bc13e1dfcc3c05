"""`btf superres train|apply` and `btf evaluate superres` on the real command line (Prefect, a Dask cluster,
real Zarr stores and torch), and the errors a user meets."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tasks.stores.btf import BtfStore, open_btf_store

SIM = ("simulate", "--device", "tiny", "--materials", "1", "--classes", "leather", "--turntable", "1",
       "--texture-size", "16", "--seed", "5")


_ROOT: list = []


@pytest.fixture
def regions(run_btf, tmp_path_factory):
    """A tiny capture ingested with and without its regions of interest (made once per session)."""
    if _ROOT:
        return _ROOT[0]
    root = tmp_path_factory.mktemp("sr-cli")
    assert run_btf(*SIM, "--out", root / "db")[0] == 0
    capture = root / "db" / "000-leather.zarr"
    assert run_btf("ingest", capture, "--out", root / "roi.zarr", "--keep-roi")[0] == 0
    assert run_btf("ingest", capture, "--out", root / "plain.zarr")[0] == 0
    _ROOT.append(root)
    return root


def test_train_then_apply(run_btf, regions):
    code, out, err = run_btf("superres", "train", regions / "roi.zarr", "--out", regions / "m.pt", "--epochs", "2",
                             progress=True)
    assert code == 0, err
    summary = json.loads(out)
    assert summary["command"] == "superres train" and summary["epochs"] <= 2 and summary["patches"] > 0
    assert "btf superres train: epoch 1: training loss" in err
    code, out, err = run_btf("superres", "apply", regions / "roi.zarr", "--model", regions / "m.pt",
                             "--out", regions / "sr.zarr")
    assert code == 0, err
    assert json.loads(out)["views_processed"] == 4
    store = open_btf_store(regions / "sr.zarr")
    assert store.texture_shape == (32, 32) and store.attrs["superres"]["method"] == "espcn"
    assert np.isfinite(store.btf[...]).all()
    code, out, _ = run_btf("validate", "--deep", regions / "sr.zarr")
    assert code == 0 and "valid" in out
    # angular resampling takes the 2x store like an ingested one
    sampling = regions / "sampling.json"
    sampling.write_text(json.dumps({"light_dirs": [[0, 0, 1], [0.3, 0, 0.95]], "view_dirs": [[0, 0, 1], [0, 0.2, 0.98]]}))
    code, out, err = run_btf("resample", regions / "sr.zarr", "--out", regions / "sr-resampled.zarr",
                             "--sampling", sampling)
    assert code == 0, err
    assert open_btf_store(regions / "sr-resampled.zarr").btf.shape == (4, 32, 32, 3)
    code, out, _ = run_btf("superres", "apply", regions / "roi.zarr", "--model", regions / "m.pt",
                           "--out", regions / "sr.zarr")
    assert code == 0 and json.loads(out)["views_skipped"] == 4                  # a finished output is reused


@pytest.mark.parametrize("case", ["no regions", "other scale", "tampered", "no patch", "nan", "stray option"])
def test_bad_input_is_one_message_and_exit_2(run_btf, regions, tmp_path, case):
    from btfcore.superres.espcn import Espcn, EspcnConfig
    from tasks.superres import save_model

    model = regions / "m.pt"
    if not model.exists():
        assert run_btf("superres", "train", regions / "roi.zarr", "--out", model, "--epochs", "1")[0] == 0
    args: tuple = ()
    if case == "no regions":
        args = ("superres", "apply", regions / "plain.zarr", "--model", model, "--out", tmp_path / "x.zarr")
        want = "plain.zarr: the store holds no regions of interest (arrays roi, homography); ingest the capture again"
    elif case == "other scale":
        config = EspcnConfig(scale=3)
        save_model(tmp_path / "x3.pt", Espcn(config).state_dict(), config, {})
        args = ("superres", "apply", regions / "roi.zarr", "--model", tmp_path / "x3.pt", "--out", tmp_path / "x.zarr")
        want = "x3.pt: a network of scale 3; this pipeline up-samples by 2"
    elif case == "tampered":
        payload = torch.load(model, weights_only=True)
        payload["state_dict"]["conv4.bias"] += 0.5
        torch.save(payload, tmp_path / "t.pt")
        args = ("superres", "apply", regions / "roi.zarr", "--model", tmp_path / "t.pt", "--out", tmp_path / "x.zarr")
        want = "t.pt: the weights do not match the file's SHA-256"
    elif case == "no patch":                       # an empty training set: every drawn region is dark
        import shutil

        shutil.copytree(regions / "roi.zarr", tmp_path / "dark.zarr")
        roi = BtfStore(tmp_path / "dark.zarr", "r+").group["roi"]
        roi[...] = np.zeros(roi.shape, roi.dtype)
        args = ("superres", "train", tmp_path / "dark.zarr", "--out", tmp_path / "p.pt")
        want = "dark.zarr: 0 of 768 training patches hold any image structure"      # 64 rows x 3 channels x 4
    elif case == "nan":
        import shutil

        shutil.copytree(regions / "roi.zarr", tmp_path / "nan.zarr")
        BtfStore(tmp_path / "nan.zarr", "r+").group["roi"][3, 10, 10, 1] = np.inf
        args = ("superres", "train", tmp_path / "nan.zarr", "--out", tmp_path / "n.pt", "--fraction", "1")
        want = "nan.zarr: 1 NaN or Inf values in roi, first at index (3, 10, 10, 1)"
    else:
        args = ("superres", "train", regions / "roi.zarr", "--out", tmp_path / "s.pt", "--model", model)
        want = "--model, --method and --overwrite belong to `btf superres apply`"
    code, out, err = run_btf(*args)
    assert code == 2, (code, err)
    assert want in err and "Traceback" not in err and out == ""
    assert not (tmp_path / "x.zarr").exists()
