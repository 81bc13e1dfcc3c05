"""Issue 13: inputs are never outputs, half-made stores resume, errors are one line before start-up.

Each test reproduces a finding of the issue on the real command line (``flows.cli.main``)
and failed on the code before the fix.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zarr

from flows.cli import EXIT_BAD_INPUT, EXIT_FAILED

ROOT = Path(__file__).resolve().parents[2]


#: A progress/info line of a run outside a terminal (flows.progress.say): timestamp, command, text.
INFO_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d btf [\w-]+: ")


def _the_one_error_line(err: str) -> bool:
    """The problem is said in exactly one line, the last; any line before it is a timestamped info line."""
    lines = err.splitlines()
    return bool(lines) and err.endswith("\n") and not INFO_LINE.match(lines[-1]) \
        and all(INFO_LINE.match(line) for line in lines[:-1])


def _tree(path: Path) -> dict[str, int]:
    """Every file under ``path`` with its size and modification time, to prove it was not touched."""
    return {str(p.relative_to(path)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(path.rglob("*"))
            if p.is_file()}


def _capture(tiny_database) -> Path:
    return sorted(tiny_database[1].glob("*.zarr"))[0]


def test_ingest_never_overwrites_its_input(run_btf, tiny_database):
    capture = _capture(tiny_database)
    before = _tree(capture)
    code, out, err = run_btf("ingest", capture, "--out", capture, "--overwrite")
    assert code == EXIT_BAD_INPUT, (out, err)
    assert f"--out {capture} is the input CAPTURE" in err and "Traceback" not in err, err
    assert _tree(capture) == before


@pytest.mark.parametrize("where", ["inside", "contains"])
def test_no_output_inside_or_around_an_input(run_btf, tiny_database, tiny_btf, where):
    capture = _capture(tiny_database)
    out = capture / "btf.zarr" if where == "inside" else capture.parent
    before = _tree(capture)
    code, _, err = run_btf("ingest", capture, "--out", out, "--overwrite")
    assert code == EXIT_BAD_INPUT and f"{where.replace('inside', 'is inside')} the input CAPTURE" in err, err
    assert _tree(capture) == before
    # the same guard serves every command: resample, export and render refuse their input too
    for argv in (("resample", tiny_btf, "--out", tiny_btf, "--overwrite"),
                 ("export-exr", tiny_btf, "--out", tiny_btf / "exr"),
                 ("render", tiny_btf, "--out", tiny_btf / "x.png")):
        code, _, err = run_btf(*argv)
        assert code == EXIT_BAD_INPUT and "the input BTF" in err, (argv, err)


def test_output_under_a_regular_file_is_one_line(run_btf, tiny_database, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    code, _, err = run_btf("ingest", _capture(tiny_database), "--out", blocker / "btf.zarr")
    assert code == EXIT_BAD_INPUT, err
    assert _the_one_error_line(err) and f"{blocker} is a file, not a folder" in err and "Traceback" not in err, err


def test_render_to_proc_is_one_line(run_btf, tiny_btf):
    code, _, err = run_btf("render", tiny_btf, "--size", "16", "--out", "/proc/x.png")
    assert code in (EXIT_BAD_INPUT, EXIT_FAILED), err
    assert err.count("\n") == 1 and "/proc/x.png" in err and "Traceback" not in err, err


@pytest.fixture()
def full_disk(tmp_path):
    """A real 256 KiB file system (tmpfs): writes past it fail with ENOSPC."""
    mount = tmp_path / "small"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mount)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here (needs root): {done.stderr.decode().strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def test_full_disk_is_a_failed_run_in_one_line(tiny_database, full_disk):
    """A real run (its own Prefect server and worker processes): neither Prefect's nor the workers'
    logs of the failed tasks stand in front of the message."""
    done = subprocess.run([sys.executable, "-m", "flows.cli", "--no-progress", "ingest", str(_capture(tiny_database)),
                           "--out", str(full_disk / "btf.zarr")], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    code, err = done.returncode, done.stderr
    assert code == EXIT_FAILED, err
    assert "No space left on device" in err and "free space or choose another --out" in err, err
    assert "Traceback" not in err and _the_one_error_line(err), err


def test_half_made_capture_store_is_rebuilt(run_btf, tmp_path):
    """What a kill between creating the store folder and writing its attributes left (before
    tasks.staging.begin_store): a root group without attributes. The rerun resumes it."""
    db = tmp_path / "db"
    half = zarr.open_group(str(db / "000-leather.zarr"), mode="w", zarr_format=3)
    half.create_array("raw", shape=(1, 1), dtype="uint16")
    (db / ".001-cloth.zarr.creating").mkdir(parents=True)          # a kill inside begin_store .. finish_store
    code, _, err = run_btf("simulate", "--materials", "2", "--turntable", "1", "--texture-size", "8",
                           "--out", db)
    assert code == 0, err
    assert not (db / ".001-cloth.zarr.creating").exists()
    assert zarr.open_group(str(db / "000-leather.zarr"), mode="r").attrs["complete"] is True


def test_refusals_name_cli_flags(run_btf, tmp_path):
    foreign = tmp_path / "db" / "000-leather.zarr"
    zarr.open_group(str(foreign), mode="w", zarr_format=3).attrs["schema"] = "something-else"
    code, _, err = run_btf("simulate", "--materials", "1", "--turntable", "1", "--out", tmp_path / "db")
    assert code == EXIT_BAD_INPUT and "--overwrite" in err and "overwrite=True" not in err.replace(
        "--overwrite (overwrite=True)", ""), err


def test_bad_manifest_fails_fast_without_traceback(tmp_path, write_dng):
    import numpy as np

    write_dng(tmp_path / "a.dng", np.full((16, 16), 500, np.uint16), "RGGB", 0.01)
    (tmp_path / "m.csv").write_text("file,turntable,camera,illumination,exposure\na.dng,0,0,0,0\nb.dng,0,0,0,1\n")
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "flows.cli", "import-raw", str(tmp_path), "--manifest",
                           str(tmp_path / "m.csv"), "--device", "tiny", "--out", str(tmp_path / "c.zarr")],
                          cwd=ROOT, capture_output=True, text=True, timeout=120, env=dict(os.environ))
    seconds = time.monotonic() - start
    assert done.returncode == EXIT_BAD_INPUT, done.stderr
    assert "b.dng" in done.stderr and "Traceback" not in done.stderr and "prefect" not in done.stderr.lower()
    assert seconds < 20, f"the manifest was refused after {seconds:.0f} s: after a cluster started?"
    assert not (tmp_path / "c.zarr").exists()


@pytest.fixture()
def unreachable_runtime(tmp_path, monkeypatch):
    """A profile whose Prefect API cannot answer: a command that reaches start-up exits 3 (runtime),
    one that refuses its input first exits 2, so the exit code shows which came first."""
    profile = tmp_path / "unreachable.yaml"
    profile.write_text("cluster: {kind: local, n_workers: 1}\nprefect: {api_url: 'http://127.0.0.1:9/api', "
                       "startup_timeout_s: 1}\n")
    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    return ["--cluster", str(profile), "--no-progress"]


def test_refusals_come_before_start_up(unreachable_runtime, tiny_database, tiny_btf, tmp_path, capsys):
    from flows.cli import EXIT_RUNTIME, main

    capture = _capture(tiny_database)
    taken = tmp_path / "taken.zarr"
    zarr.open_group(str(taken), mode="w", zarr_format=3).attrs["schema"] = "something-else"
    (tmp_path / "classes.json").write_text("[1, 2]")
    cases = {
        "ingest into another store": ["ingest", capture, "--out", taken],
        "simulate into another store": ["simulate", "--materials", "1", "--out", tmp_path / "sim"],
        "build-db with a bad class map": ["build-db", tiny_btf.parent, "--out", tmp_path / "m",
                                          "--classes", tmp_path / "classes.json"],
        "build-db of a folder without stores": ["build-db", tmp_path / "empty", "--out", tmp_path / "m"],
        "resample of no store": ["resample", tmp_path / "none.zarr", "--out", tmp_path / "r.zarr"],
    }
    (tmp_path / "empty").mkdir()
    zarr.open_group(str(tmp_path / "sim" / "000-leather.zarr"), mode="w", zarr_format=3).attrs["schema"] = "x"
    for name, argv in cases.items():
        capsys.readouterr()
        code = main([*unreachable_runtime, *map(str, argv)])
        err = capsys.readouterr().err
        assert code == EXIT_BAD_INPUT, (name, code, err)
        assert "Traceback" not in err, (name, err)
    # and the runtime itself is only reached by a command whose input is fine
    assert main([*unreachable_runtime, "ingest", str(capture), "--out", str(tmp_path / "fine.zarr")]) == EXIT_RUNTIME
