"""Issue 20 study (not a speed benchmark): where the fixed n_s = 400 error sits against the class basis' floor.

Bar 1 asks the adaptive loop to reach the fixed optimised sampling's n_s = 400 error in half its shots. This
computes, for every held-out material of the structured classes, the **floor** of its leave-one-out class basis
(:func:`btfcore.acquisition.adaptive.basis_floor`, which the evaluation's records hold since
``ADAPTIVE_VERSION`` 8): the error of the loop's solve (relative row weights, the Tikhonov term of paper 4
eq. 10, every row from the basis) when *every* row is measured without noise. No sampling of rows reaches under
it without the measured rows' own values (the loop and the fixed samplings fuse them, ``--rows fused``), and each
shot measures ``n_cam`` of the ``n_lv`` rows. It prints the floor beside the fixed n_s = 400 error and the loop's
shots to that error, read from the evaluation's report.json (``--seed``, ``--materials-per-class`` and
``--turntable`` as the evaluation's). About a second a material.

    PYTHONPATH=benchmarks .venv/bin/python benchmarks/study_adaptive_floor.py --db acq-db --eval acq [--seed 0]
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import zarr

from study_adaptive_predictor import replay_materials, replay_parser
from btfcore.acquisition.adaptive import basis_floor
from tasks.adaptive import THESIS_N_S, shots_to_reach
from tasks.evaluate_acquisition.graph import leave_one_out_bases, material_geometry

STRUCTURED = ("carpet", "stone", "leather")


def main() -> None:
    a = replay_parser(__doc__).parse_args()
    config, materials, chosen = replay_materials(a)
    records = json.loads((Path(a.eval) / "report.json").read_text())["adaptive"]["materials"]
    out = {}
    print(f"{'material':<14}{'k':>4}{'floor':>9}{'fixed n400':>12}{'n400 / floor':>14}{'loop shots':>12}")
    for m in chosen:
        rec = records[m.material_id]
        if rec["class"] not in STRUCTURED:
            continue
        als = leave_one_out_bases(f"{a.eval}/model.zarr", materials, m.material_id, config.model_settings())["als"]
        truth = np.asarray(zarr.open_group(m.path, mode="r", zarr_format=3)["btf"][...], dtype=np.float32)
        truth = truth.reshape(truth.shape[0], -1, 3)
        floor = basis_floor(np.asarray(als.U, dtype=np.float64), np.asarray(als.sigma, dtype=np.float64),
                            material_geometry(m), truth)
        target = next(f["error"] for f in rec["fixed"] if f["n_thesis"] == THESIS_N_S[-1])
        shots = shots_to_reach(rec["steps"], target)
        out[m.material_id] = {"class": rec["class"], "k": int(len(als.sigma)), "floor": floor, "fixed_n400": target,
                              "loop_shots": shots, "budget": len(rec["steps"])}
        print(f"{m.material_id:<14}{len(als.sigma):>4}{100 * floor:>8.2f}%{100 * target:>11.2f}%"
              f"{target / floor:>14.2f}{shots or 'never':>12}", flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
