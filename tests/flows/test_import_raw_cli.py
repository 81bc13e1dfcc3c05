"""`btf import-raw` end to end: real DNG files, real LibRaw, Prefect and a LocalCluster."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def test_import_raw_lists_problems_then_imports(tmp_path, write_dng, runtime_session):
    rng = np.random.default_rng(2)
    lines = ["file,turntable,camera,illumination,exposure"]
    for i in range(2):
        for e in range(2):
            name = f"l{i}_e{e}.dng"
            write_dng(tmp_path / name, rng.integers(64, 4000, (72, 80), dtype=np.uint16), "RGGB", 0.01 * 8**e)
            lines.append(f"{name},0,0,{i},{e}")
    import cv2

    assert cv2.imwrite(str(tmp_path / "photo.png"), np.zeros((8, 8, 3), np.uint8))   # an image, not raw
    (tmp_path / "manifest.csv").write_text("\n".join(lines + ["ghost.dng,0,0,1,1", "photo.png,0,0,0,0"]) + "\n")
    cmd = [sys.executable, "-m", "flows.cli", "import-raw", str(tmp_path), "--manifest",
           str(tmp_path / "manifest.csv"), "--device", "tiny", "--out", str(tmp_path / "c.zarr")]
    bad = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300, env=dict(os.environ))
    assert bad.returncode == 2
    assert "ghost.dng): file not found" in bad.stderr and "duplicate entry" in bad.stderr
    assert "photo.png): a PNG image, not a camera raw file" in bad.stderr and "Traceback" not in bad.stderr
    assert not (tmp_path / "c.zarr").exists()
    (tmp_path / "manifest.csv").write_text("\n".join(lines) + "\n")
    good = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300,   # the session's Prefect
                          env={**os.environ, "PREFECT_API_URL": runtime_session[1]})
    assert good.returncode == 0, good.stderr[-3000:]
    result = json.loads(good.stdout)
    assert result["complete"] and result["shape"] == [1, 1, 2, 2] and result["bayer_pattern"] == "RGGB"
    check = subprocess.run([sys.executable, "-m", "flows.cli", "validate", str(tmp_path / "c.zarr")],
                           cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert check.returncode == 0 and "valid" in check.stdout
