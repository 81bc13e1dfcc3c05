"""Issue 19, item 4: the bad-input catalogue on the real command line.

Each case spoils one input in one way and runs the real ``btf`` command as a subprocess
(``python -m flows.cli``): it must exit with the bad-input code (2), and its stderr must hold
the message and nothing else: any line before it is one of the command's own timestamped
info lines (``btf ingest: checking the inputs ...``), the message's first line is
``btf COMMAND: ...``, every further line is indented (a list of problems), and there is no
traceback and no log line of Prefect or Dask. The message names the file (and the array and
index where there is one) and says what to do; the key words checked are those of the table
in docs/bad-inputs.md, which also lists the cases other test files check. Most cases fail
before any cluster starts; the few that are found while the data is read (``on_cluster``) run
on the session's Prefect server and a threaded one-worker cluster.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zarr

from btf_env import btf_environ
from flows.cli import EXIT_BAD_INPUT

ROOT = Path(__file__).resolve().parents[2]

#: A line ``flows.progress.say`` prints outside a terminal: a timestamp, then the command or stage.
INFO_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d \S")
#: What must never reach the user: a traceback, Prefect's or Dask's log records.
NOISE = ("Traceback", "prefect.", "distributed.", "| ERROR", "| WARNING")


@dataclass(frozen=True)
class Inputs:
    """Good inputs made once per module; a case copies what it spoils into its own folder."""

    capture: Path          # btf-capture store: tiny, 1 turntable position x 4 cameras x 16 LEDs
    btf: Path              # its btf-texture store (`btf ingest`)
    model: Path            # a `btf build-db` folder: model.zarr with classes/leather/{als,log_y}, k = 8
    measurement: Path      # btf-measurement store: every second row of the BTF measured


@dataclass(frozen=True)
class Case:
    """One bad input: its category of issue 19 and ``make(inputs, tmp) -> (argv, needles)``.

    ``needles`` must all be in the message: the first names the file, array or index, the last
    is the fix.
    """

    category: str
    make: Callable[[Inputs, Path], tuple[list, list[str]]]
    on_cluster: bool = False


def _copy(src: Path, tmp: Path, name: str | None = None) -> Path:
    return Path(shutil.copytree(src, tmp / (name or src.name)))


def _spoil(store: Path, array: str, index: tuple, value: float) -> None:
    """``store[array][index] = value`` on the whole (small) array."""
    a = zarr.open_group(str(store), mode="r+", zarr_format=3)[array]
    data = a[...]
    data[index] = value
    a[...] = data


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- corrupt, truncated or foreign files

def _text_as_capture(i: Inputs, tmp: Path):
    bad = _write(tmp / "notes.zarr", "a text file, not a store\n")
    return ["ingest", bad, "--out", tmp / "o.zarr"], [f"{bad}: <store>", "this is not a capture store; check the path"]


def _btf_as_capture(i: Inputs, tmp: Path):
    return (["ingest", i.btf, "--out", tmp / "o.zarr"],
            [f"{i.btf}: attrs[schema]: expected 'btf-capture'; found 'btf-texture'", "give the capture store"])


def _capture_to_render(i: Inputs, tmp: Path):
    return (["render", i.capture, "--out", tmp / "o.png"],
            [f"{i.capture} is not a BTF store (schema 'btf-capture'", "give the output of `btf ingest`"])


def _text_as_model(i: Inputs, tmp: Path):
    bad = _write(tmp / "model.zarr", "{}")
    return (["sample", "--model", bad, "--class", "leather", "--n", "10", "--out", tmp / "s.json"],
            [f"{bad}: not a readable Zarr group", "give the --out folder of `btf build-db`"])


def _zip_as_dng(i: Inputs, tmp: Path):
    import zipfile

    folder = tmp / "raw"
    folder.mkdir()
    with zipfile.ZipFile(folder / "a.dng", "w") as z:
        z.writestr("a.txt", "not a raw file")
    manifest = _write(folder / "m.csv", "file,turntable,camera,illumination,exposure\na.dng,0,0,0,0\n")
    return (["import-raw", folder, "--manifest", manifest, "--device", "tiny", "--out", tmp / "c.zarr"],
            [f"{manifest}:2 (a.dng): LibRaw cannot read it", "re-copy it from the camera"])


def _text_as_bonn_file(i: Inputs, tmp: Path):
    bad = _write(tmp / "leather.btf", "hello\n")
    return (["import-btf", bad, "--out", tmp / "o.zarr"],
            [f"{bad}: byte 0, signature: unknown signature", "this is not a Bonn BTF file"])


def _truncated_plan(i: Inputs, tmp: Path):
    bad = _write(tmp / "plan.json", '{"schema": "btf-plan", "shots": [')
    return (["simulate", "--plan", bad, "--device", "tiny", "--materials", "1", "--out", tmp / "db"],
            [f"{bad}: not a plan JSON file", "write it with tasks.plan.write_plan"])


def _text_as_exr(i: Inputs, tmp: Path):
    bad = _write(tmp / "sky.exr", "not an image")
    return (["render", i.btf, "--env", bad, "--size", "16", "--out", tmp / "o.png"],
            [f"{bad} is not a readable OpenEXR file", "give a latitude-longitude HDR map in OpenEXR format"])


def _truncated_btf_chunk(i: Inputs, tmp: Path):
    btf = _copy(i.btf, tmp)
    chunk = btf / "btf" / "c" / "2" / "0" / "0" / "0"
    chunk.write_bytes(chunk.read_bytes()[:50])
    return (["export-exr", btf, "--out", tmp / "exr", "--lv", "0-63"],
            [f"{btf}: array btf, chunk (2, 0, 0, 0): truncated", "btf ingest --overwrite"])


# --------------------------------------------------------------------------- missing or contradictory metadata

def _no_view_dir(i: Inputs, tmp: Path):
    btf = _copy(i.btf, tmp)
    shutil.rmtree(btf / "view_dir")
    return (["render", btf, "--size", "16", "--out", tmp / "o.png"],
            [f"{btf}: arrays ['view_dir'] are missing", "write the store again with `btf ingest`"])


def _unfinished_btf(i: Inputs, tmp: Path):
    btf = _copy(i.btf, tmp)
    zarr.open_group(str(btf), mode="r+", zarr_format=3).attrs["complete"] = False
    return (["render", btf, "--size", "16", "--out", tmp / "o.png"],
            [f"{btf} is an unfinished BTF store (attribute complete is false)", "to resume"])


def _manifest_without_column(i: Inputs, tmp: Path):
    folder = tmp / "raw"
    folder.mkdir()
    manifest = _write(folder / "m.csv", "file,turntable,camera,exposure\na.dng,0,0,0\n")
    return (["import-raw", folder, "--manifest", manifest, "--device", "tiny", "--out", tmp / "c.zarr"],
            [f"{manifest}: the header lacks column(s) illumination", "expected file,turntable,camera,illumination"])


def _sampling_without_views(i: Inputs, tmp: Path):
    bad = _write(tmp / "sampling.json", '{"light_dirs": [[0, 0, 1]]}')
    return (["resample", i.btf, "--sampling", bad, "--out", tmp / "r.zarr"],
            [f"{bad}", "view_dirs", '{"light_dirs": [[x, y, z], ...], "view_dirs"'])


def _samples_without_pairs(i: Inputs, tmp: Path):
    bad = _write(tmp / "s.json", '{"schema": "btf-samples", "rows": [1, 2, 3]}')
    return (["plan", "--device", "tiny", "--strategy", "sparse", "--samples", bad, "--out", tmp / "p"],
            [f"{bad}: holds no (turntable, LED) pairs", "run `btf sample ... --device tiny`"])


# --------------------------------------------------------------------------- NaN/Inf in every kind of store and file

def _nan_turntable_angle(i: Inputs, tmp: Path):
    capture = _copy(i.capture, tmp)
    _spoil(capture, "turntable_angle", (0,), np.nan)
    return (["ingest", capture, "--out", tmp / "o.zarr"],
            [f"{capture}: turntable_angle[(turntable,)=(0)]", "check the device calibration"])


def _inf_btf_texel_render(i: Inputs, tmp: Path):
    btf = _copy(i.btf, tmp)
    _spoil(btf, "btf", (7, 0, 1, 2), np.inf)
    return (["render", btf, "--size", "16", "--out", tmp / "o.png"],
            [f"{btf}: btf[7, 0, 1, 2] = inf", "write the store again with the command that wrote it"])


def _inf_light_dir(i: Inputs, tmp: Path):
    btf = _copy(i.btf, tmp)
    _spoil(btf, "light_dir", (3, 1), np.inf)
    return (["resample", btf, "--out", tmp / "r.zarr"],
            [f"{btf}: light_dir[3] = [", "write the store again with `btf ingest` into a new --out"])


def _nan_in_G(i: Inputs, tmp: Path):
    meas = _copy(i.measurement, tmp)
    _spoil(meas, "G", (3, 6), np.nan)
    return (["reconstruct", meas, "--model", i.model, "--class", "leather", "--method", "tikhonov",
             "--out", tmp / "r.zarr"],
            [f"{meas}: G[3, 6] = nan is not finite", "ingest the plan capture again"])


def _inf_in_measured(i: Inputs, tmp: Path):
    meas = _copy(i.measurement, tmp)
    _spoil(meas, "measured", (3, 6, 1, 0), np.inf)
    return (["reconstruct", meas, "--model", i.model, "--class", "leather", "--method", "tikhonov",
             "--out", tmp / "r.zarr"],
            [f"{meas}: measured[3, 6, 1, 0] = inf", "write the input again with `btf ingest`"])


def _nan_in_basis(i: Inputs, tmp: Path):
    model = _copy(i.model, tmp)
    _spoil(model / "model.zarr", "classes/leather/als/U", (5, 1), np.nan)
    return (["reconstruct", i.measurement, "--model", model, "--class", "leather", "--method", "tikhonov",
             "--out", tmp / "r.zarr"],
            [f"{model}: classes/leather/als/U[5, 1] = nan is not finite", "rebuild the model with `btf build-db`"])


def _nan_in_sampling_file(i: Inputs, tmp: Path):
    bad = _write(tmp / "sampling.json", '{"light_dirs": [[0, 0, 1]], "view_dirs": [[0, NaN, 1]]}')
    return (["resample", i.btf, "--sampling", bad, "--out", tmp / "r.zarr"],
            [f"{bad}: 1 problem(s) in the sampling file", "view_dirs[0] = [0, nan, 1] is not finite", "Fix them"])


def _nan_in_plan(i: Inputs, tmp: Path):
    from btfcore.acquisition.plan import full_single_light_plan
    from btfcore.dome import get_device
    from tasks.plan import write_plan

    device = get_device("tiny")
    write_plan(full_single_light_plan(device), tmp / "good.json", device=device)
    doc = json.loads((tmp / "good.json").read_text())
    doc["shots"][2]["shutter_ms"][1] = float("nan")
    bad = _write(tmp / "plan.json", json.dumps(doc))
    return (["simulate", "--plan", bad, "--device", "tiny", "--materials", "1", "--out", tmp / "db"],
            [f"{bad}: plan shot 2: Shot.shutter_ms must be finite", "> 0 ms"])


def _nan_in_samples(i: Inputs, tmp: Path):
    bad = _write(tmp / "s.json", '{"schema": "btf-samples", "device": "tiny", "pairs": [[0, NaN], [1, 2]]}')
    return (["plan", "--device", "tiny", "--strategy", "sparse", "--samples", bad, "--out", tmp / "p"],
            [f"{bad}: pairs[0] = [0, nan]", "write the file again with `btf sample ... --device DEVICE`"])


def _nan_in_calibration(i: Inputs, tmp: Path):
    from btfcore.dome import get_device

    device = get_device("tiny").to_json()
    device["turntable_angle_deg"][1] = float("nan")
    bad = _write(tmp / "dome.json", json.dumps(device))
    folder = tmp / "raw"
    folder.mkdir()
    manifest = _write(folder / "m.csv", "file,turntable,camera,illumination,exposure\na.dng,0,0,0,0\n")
    return (["import-raw", folder, "--manifest", manifest, "--calibration", bad, "--out", tmp / "c.zarr"],
            [f"{bad}: not a valid dome calibration", "turntable_angle_deg contains NaN or Inf at [1]",
             "write it again with Device.to_json"])


def _nan_in_env_map(i: Inputs, tmp: Path):
    import OpenEXR

    pixels = np.ones((4, 8, 3), np.float32)
    pixels[1, 2, 0] = np.nan
    bad = tmp / "sky.exr"
    with OpenEXR.File({"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"RGB": pixels}) as f:
        f.write(str(bad))
    return (["render", i.btf, "--env", bad, "--size", "16", "--out", tmp / "o.png"],
            [f"{bad}: pixel [1, 2, 0] is nan", "an environment map must be finite"])


# --------------------------------------------------------------------------- all-saturated or all-dark frames

def _dark_white_standard(i: Inputs, tmp: Path):
    white = _copy(i.btf, tmp, "white.zarr")
    btf = zarr.open_group(str(white), mode="r+", zarr_format=3)["btf"]
    btf[...] = np.zeros(btf.shape, np.float32)
    return (["ingest", i.capture, "--white", white, "--out", tmp / "o.zarr"],
            [f"{white}: btf rows 0-15 (turntable 0, camera 0): LED 0 channel 0 has gain 0",
             "capture the white standard again with every LED lighting it"])


# --------------------------------------------------------------------------- mismatched devices, samplings, calibrations, bases

def _model_of_another_sampling(i: Inputs, tmp: Path):
    model = _copy(i.model, tmp)
    light = zarr.open_group(str(model / "model.zarr"), mode="r+", zarr_format=3)["light_dir"]
    rows = light[...]
    light[...] = rows[[1, 0, *range(2, len(rows))]]                 # two light directions swapped
    return (["reconstruct", i.measurement, "--model", model, "--class", "leather", "--method", "tikhonov",
             "--out", tmp / "r.zarr"],
            [f"{i.measurement}: light/view pair 0 differs from the model's", "use a model of this device's sampling"])


def _white_of_another_dome(i: Inputs, tmp: Path):
    from tasks.stores.btf import LV_ORDER, band_rows, create_btf_store

    source = zarr.open_group(str(i.btf), mode="r", zarr_format=3)
    rows = [c * 16 + led for c in range(4) for led in range(8)]      # the same cameras, 8 of the 16 LEDs
    light, view = source["light_dir"][...][rows], source["view_dir"][...][rows]
    lv_index = np.indices((1, 4, 8)).reshape(3, -1).T.astype(np.int32)
    white = tmp / "white-8-leds.zarr"
    store = create_btf_store(white, {"units": source.attrs["units"], "lv_order": LV_ORDER, "ingest_hash": "white-8",
                                     "turntable_cameras_leds": [1, 4, 8]},
                             light_dir=light, view_dir=view, lv_index=lv_index, texture_shape=(8, 8),
                             rows_per_chunk=8, band=band_rows(8, 8, 8), written_shape=(1, 4),
                             valid_fraction_shape=(1, 4, 8))
    store.btf[...] = np.broadcast_to(0.5 * light[:, 2, None, None, None], (32, 8, 8, 3)).astype(np.float32)
    store.group["written"][...] = 1
    store.mark_complete()
    return (["ingest", i.capture, "--white", white, "--out", tmp / "o.zarr"],
            [f"{white}: the white standard has 8 LEDs, the capture {i.capture} 16",
             "calibrate with a white standard captured on the same dome"])


def _database_of_two_samplings(i: Inputs, tmp: Path):
    db = tmp / "db"
    for n, name in enumerate(("000-leather", "001-leather")):
        store = _copy(i.btf, db, f"{name}.zarr")
        group = zarr.open_group(str(store), mode="r+", zarr_format=3)
        group.attrs["material"] = {"material_id": name, "class": "leather"}
        if n:
            light = group["light_dir"]
            light[...] = light[...][[*range(5), 6, 5, *range(7, light.shape[0])]]
    return (["build-db", db, "--out", tmp / "model"],
            [f"{db / '001-leather.zarr'}: another light/view sampling (light_dir/view_dir[5] differ",
             "resample both to one sampling (btf resample)"])


def _plan_of_another_device(i: Inputs, tmp: Path):
    from btfcore.acquisition.plan import full_single_light_plan
    from btfcore.dome import get_device
    from tasks.plan import write_plan

    plan = tmp / "plan.json"
    write_plan(full_single_light_plan(get_device("tiny")), plan, device=get_device("tiny"))
    return (["simulate", "--plan", plan, "--device", "bonn-dome2", "--materials", "1", "--out", tmp / "db"],
            ["the plan was made for device 'tiny', the simulation is of 'bonn-dome2'", "pass --device tiny"])


def _more_basis_vectors_than_the_model_has(i: Inputs, tmp: Path):
    return (["reconstruct", i.measurement, "--model", i.model, "--class", "leather", "--method", "tikhonov",
             "--k", "50", "--out", tmp / "r.zarr"],
            [f"{i.model}: classes/leather/als has 8 basis vectors, k=50 asked", "choose k <= 8"])


# --------------------------------------------------------------------------- invalid S-matrix orders

def _plan_with_group(group: str | None, order: int | None):
    def make(i: Inputs, tmp: Path):
        from btfcore.acquisition.plan import multiplexed_plan
        from btfcore.dome import get_device
        from tasks.plan import write_plan

        device = get_device("tiny")
        write_plan(multiplexed_plan(device), tmp / "good.json", device=device)
        doc = json.loads((tmp / "good.json").read_text())
        for shot in doc["shots"]:
            shot["group"] = group or shot["group"]
        if order is not None:
            doc["parameters"]["s_matrix_order"] = order
        bad = _write(tmp / "plan.json", json.dumps(doc))
        where = f"shot 0 (group '{group}')" if group else "parameters.s_matrix_order"
        n = int(group[1:]) if group else order
        return (["simulate", "--plan", bad, "--device", "tiny", "--materials", "1", "--out", tmp / "db"],
                [f"{bad}: {where}: no quadratic-residue S-matrix of order {n}", "nearest valid orders",
                 "write the plan again with `btf plan`"])
    return make


# --------------------------------------------------------------------------- too few samples

def _too_few_camera_parallel_pairs(i: Inputs, tmp: Path):
    return (["sample", "--model", i.model, "--class", "leather", "--basis", "als", "--camera-parallel", "--n", "1",
             "--out", tmp / "s.json"],
            [f"{i.model / 'model.zarr'}: classes/leather/als (U 64 x 8): n_s=1 groups measure at most 4 rows",
             "pass a larger n_s (at least 2)"])


# --------------------------------------------------------------------------- crafted names and symlinks

def _manifest_names(name: str):
    def make(i: Inputs, tmp: Path):
        folder = tmp / "raw"
        folder.mkdir()
        (tmp / "x.dng").write_bytes(b"outside the folder")
        manifest = _write(folder / "m.csv", f"file,turntable,camera,illumination,exposure\n{name.format(tmp=tmp)},"
                                            "0,0,0,0\n")
        return (["import-raw", folder, "--manifest", manifest, "--device", "tiny", "--out", tmp / "c.zarr"],
                [f"{manifest}:2 ({name.format(tmp=tmp)}): names a file outside {folder}",
                 "copy or move the file into the folder"])
    return make


def _symlink_in_output(command: str):
    def make(i: Inputs, tmp: Path):
        out, outside = tmp / "out", tmp / "elsewhere"
        out.mkdir()
        outside.mkdir()
        name, argv = (("lv00000_t0_c0_l0.exr", ["export-exr", i.btf, "--lv", "0"]) if command == "export-exr"
                      else ("plan.json", ["plan", "--device", "tiny", "--strategy", "full"]))
        (out / name).symlink_to(outside / name)
        return ([*argv, "--out", out],
                [f"--out {out}: {name} is a symbolic link to {outside / name}, outside the output",
                 "remove the link or choose another --out"])
    return make


def _symlink_deep_in_a_store(i: Inputs, tmp: Path):
    """An unfinished output store whose chunk folder is a link out of it: a resumed run would write there."""
    out, outside = tmp / "out.zarr", tmp / "elsewhere"
    (out / "btf").mkdir(parents=True)
    outside.mkdir()
    (out / "btf" / "c").symlink_to(outside)
    return (["ingest", i.capture, "--out", out],
            [f"--out {out}: btf/c is a symbolic link to {outside}, outside the output",
             "remove the link or choose another --out"])


def _class_as_path(i: Inputs, tmp: Path):
    return (["sample", "--model", i.model, "--class", "../leather", "--n", "20", "--out", tmp / "s.json"],
            [f"{i.model / 'model.zarr'}: no class '../leather' in the model store (classes/: leather)",
             "pass one of them as --class"])


# --------------------------------------------------------------------------- malformed execution profiles

def _profile(text: str | None, message: str, fix: str, via_environment: bool = False):
    def make(i: Inputs, tmp: Path):
        profile = tmp / "profile.yaml"
        if text is not None:
            profile.write_text(text)
        argv = ["ingest", i.capture, "--out", tmp / "o.zarr"]
        if via_environment:
            return argv, [f"execution profile {profile}", message, fix], {"BTF_CLUSTER_CONFIG": str(profile)}
        return [*argv, "--cluster", profile], [f"execution profile {profile}", message, fix]
    return make


CASES: dict[str, Case] = {
    "text file as a capture store": Case("corrupt, truncated or foreign file", _text_as_capture),
    "BTF store as a capture store": Case("corrupt, truncated or foreign file", _btf_as_capture),
    "capture store as a BTF store": Case("corrupt, truncated or foreign file", _capture_to_render),
    "text file as a model store": Case("corrupt, truncated or foreign file", _text_as_model),
    "zip archive named .dng": Case("corrupt, truncated or foreign file", _zip_as_dng),
    "text file as a Bonn BTF file": Case("corrupt, truncated or foreign file", _text_as_bonn_file),
    "truncated plan JSON": Case("corrupt, truncated or foreign file", _truncated_plan),
    "text file as an EXR environment map": Case("corrupt, truncated or foreign file", _text_as_exr),
    "truncated chunk of a BTF store": Case("corrupt, truncated or foreign file", _truncated_btf_chunk),
    "BTF store without view_dir": Case("missing or contradictory metadata", _no_view_dir),
    "unfinished BTF store": Case("missing or contradictory metadata", _unfinished_btf),
    "manifest without an illumination column": Case("missing or contradictory metadata", _manifest_without_column),
    "sampling file without view_dirs": Case("missing or contradictory metadata", _sampling_without_views),
    "samples file without (turntable, LED) pairs": Case("missing or contradictory metadata", _samples_without_pairs),
    "NaN turntable angle in a capture store": Case("NaN/Inf", _nan_turntable_angle),
    "Inf texel in a BTF store (render)": Case("NaN/Inf", _inf_btf_texel_render),
    "Inf light direction in a BTF store": Case("NaN/Inf", _inf_light_dir),
    "NaN in a measurement store's G": Case("NaN/Inf", _nan_in_G),
    "Inf in a measurement store's textures": Case("NaN/Inf", _inf_in_measured, on_cluster=True),
    "NaN in a model store's basis": Case("NaN/Inf", _nan_in_basis),
    "NaN in a sampling file": Case("NaN/Inf", _nan_in_sampling_file),
    "NaN shutter time in a plan file": Case("NaN/Inf", _nan_in_plan),
    "NaN in a samples file": Case("NaN/Inf", _nan_in_samples),
    "NaN turntable angle in a dome calibration": Case("NaN/Inf", _nan_in_calibration),
    "NaN pixel in an environment map": Case("NaN/Inf", _nan_in_env_map),
    "all-dark white standard": Case("all-saturated or all-dark frames", _dark_white_standard),
    "model of another light/view sampling": Case("mismatched device, sampling, calibration or basis",
                                                 _model_of_another_sampling),
    "white standard of a dome with other LEDs": Case("mismatched device, sampling, calibration or basis",
                                                     _white_of_another_dome),
    "database of two samplings": Case("mismatched device, sampling, calibration or basis",
                                      _database_of_two_samplings),
    "plan of another device": Case("mismatched device, sampling, calibration or basis", _plan_of_another_device),
    "more basis vectors than the model has": Case("mismatched device, sampling, calibration or basis",
                                                  _more_basis_vectors_than_the_model_has),
    "plan group S8 (not prime)": Case("invalid S-matrix order", _plan_with_group("S8", None)),
    "plan group S13 (prime, 13 % 4 == 1)": Case("invalid S-matrix order", _plan_with_group("S13", None)),
    "plan s_matrix_order 15": Case("invalid S-matrix order", _plan_with_group(None, 15)),
    "too few camera-parallel pairs for the basis": Case("too few samples", _too_few_camera_parallel_pairs),
    "manifest naming ../x.dng": Case("crafted name or symlink", _manifest_names("../x.dng")),
    "manifest naming an absolute path": Case("crafted name or symlink", _manifest_names("{tmp}/x.dng")),
    "symlink out of the export-exr folder": Case("crafted name or symlink", _symlink_in_output("export-exr")),
    "symlink out of the plan folder": Case("crafted name or symlink", _symlink_in_output("plan")),
    "symlink deep in an output store": Case("crafted name or symlink", _symlink_deep_in_a_store),
    "--class ../leather": Case("crafted name or symlink", _class_as_path),
    "profile that is not YAML": Case("malformed profile", _profile(
        "cluster: [unclosed\n", "is not valid YAML (line 2, column 1", "a profile holds plain keys and values only")),
    "profile with a misspelt key": Case("malformed profile", _profile(
        "cluster: {kind: local, n_worker: 4}\n", "unknown key 'cluster.n_worker' for cluster kind 'local'",
        "allowed keys: kind, n_workers")),
    "profile that does not exist": Case("malformed profile", _profile(
        None, "does not exist", "pass --cluster with a file shaped like")),
    "profile with a python tag": Case("malformed profile", _profile(
        "cluster: !!python/object/apply:os.system ['touch pwned']\n", "could not determine a constructor for the tag",
        "a profile holds plain keys and values only")),
    "BTF_CLUSTER_CONFIG: slurm profile without memory": Case("malformed profile", _profile(
        "cluster: {kind: slurm, cores: 1}\n", "cluster kind 'slurm' needs 'cluster.memory'", "see infra/slurm.yaml",
        via_environment=True)),
}


@pytest.fixture(scope="module")
def inputs(tiny_btf, tmp_path_factory) -> Inputs:
    """The session's tiny capture and BTF store, a model fitted on the BTF store (the SVD of its rows,
    as `btf build-db`'s store lays it out) and a measurement of every second row."""
    from btfcore.acquisition.reconstruct import measurement_matrix
    from tasks.stores.measurement import write_measurement

    root = tmp_path_factory.mktemp("catalogue")
    source = zarr.open_group(str(tiny_btf), mode="r", zarr_format=3)
    B = np.asarray(source["btf"][...], dtype=np.float64)
    n_lv = B.shape[0]
    U, sigma, _ = np.linalg.svd(B.reshape(n_lv, -1), full_matrices=False)
    model = zarr.open_group(str(root / "model" / "model.zarr"), mode="w", zarr_format=3)
    for name in ("light_dir", "view_dir"):
        model.create_array(name, data=source[name][...])
    model.attrs.put({"schema": "btf-model", "schema_version": "1.0", "rows_id": "catalogue", "n_lv": n_lv})
    for basis in ("als", "log_y"):
        group = model.require_group(f"classes/leather/{basis}")
        group.create_array("U", data=U[:, :8])
        group.create_array("sigma", data=sigma[:8])
        group.attrs.put({"method": "test", "key": f"svd-{basis}"})
    G = measurement_matrix(n_lv, rows=np.arange(0, n_lv, 2))
    G = np.asarray(G.todense() if hasattr(G, "todense") else G)
    write_measurement(root / "measurement.zarr", (G @ B.reshape(n_lv, -1)).reshape(len(G), *B.shape[1:]), G,
                      source["light_dir"][...], source["view_dir"][...], tuple(source.attrs["turntable_cameras_leds"]))
    capture = next(p for p in tiny_btf.parent.glob("*.zarr")
                   if zarr.open_group(str(p), mode="r").attrs.get("schema") == "btf-capture")
    return Inputs(capture=capture, btf=tiny_btf, model=root / "model", measurement=root / "measurement.zarr")


def _message(stderr: str) -> tuple[str, str]:
    """``(first line, whole message)`` of stderr after the command's own info lines; fails on anything else."""
    lines = stderr.splitlines()
    start = next((n for n, line in enumerate(lines) if not INFO_LINE.match(line)), len(lines))
    assert start < len(lines), f"no message, only info lines: {stderr!r}"
    rest = lines[start + 1:]
    assert all(line.startswith((" ", "\t")) or not line.strip() or line.startswith("Fix") for line in rest), \
        f"lines after the message that are not part of it: {stderr!r}"
    return lines[start], "\n".join(lines[start:])


@pytest.mark.parametrize("case", list(CASES))
def test_a_bad_input_is_named_with_its_fix_in_one_message(case, inputs, tmp_path, runtime_session):
    spec = CASES[case]
    made = spec.make(inputs, tmp_path)
    argv, needles, extra_env = (*made, {}) if len(made) == 2 else made
    extra = []
    if spec.on_cluster:             # the session's Prefect server and a threaded one-worker cluster
        profile = _write(tmp_path / "threads.yaml", "cluster: {kind: local, n_workers: 1, threads_per_worker: 1, "
                                                    "processes: false}\n")
        extra, extra_env = ["--cluster", profile], {**extra_env, "PREFECT_API_URL": runtime_session[1]}
    done = subprocess.run([sys.executable, "-m", "flows.cli", "--no-progress", *extra, *map(str, argv)], cwd=ROOT,
                          capture_output=True, text=True, timeout=180,
                          env=btf_environ(tmp_path / "state", **extra_env))
    assert done.returncode == EXIT_BAD_INPUT, (done.returncode, done.stderr[-3000:])
    assert not any(noise in done.stderr for noise in NOISE), done.stderr
    first, message = _message(done.stderr)
    assert first.startswith(f"btf {argv[0]}: "), (first, done.stderr)
    for needle in needles:
        assert needle in message, f"{needle!r} not in {message!r}"
    assert done.stdout == ""


def test_the_catalogue_covers_every_category_of_the_issue():
    categories = {case.category for case in CASES.values()}
    assert categories == {"corrupt, truncated or foreign file", "missing or contradictory metadata", "NaN/Inf",
                          "all-saturated or all-dark frames", "mismatched device, sampling, calibration or basis",
                          "invalid S-matrix order", "too few samples", "crafted name or symlink",
                          "malformed profile"}
    assert len(CASES) >= 40
