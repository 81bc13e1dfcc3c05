"""Benchmark: weak and strong scaling of `btf ingest` and `btf build-db` on 1 and 2 Dask workers of an
execution profile (the Slurm profile by default: each worker one Slurm job), and the per-chunk costs that
docs/scaling.md projects to a thesis-scale database from.

Data (simulated, prepared once on a threaded cluster, not timed):

* ingest: one material's capture of ``--turntable`` T positions on ``--device`` (bonn-dome2: 11 views of
  198 single-LED brackets of 4 raw frames each per position, 1.4 GB of raw frames), and one of 2T
  positions; `btf ingest` runs one Dask task per view;
* build-db: ``--materials`` M ingested materials of the `tiny` dome (one turntable position, 64 light/view
  pairs, ``--db-texture`` px; leather and cloth, M/2 each), and 2M; `btf build-db`
  runs one Dask task per material for the bases and one per material for the leave-one-out evaluation,
  with the merges in the client between them.

For each worker count N in (1, 2) the profile's cluster is started with N workers (a Slurm profile with
``minimum_jobs = maximum_jobs = N``; a local one with ``n_workers = N``), its start timed until N workers
answer; then the stages run on it as the commands run them (:func:`tasks.ingest.ingest_capture`,
:func:`tasks.model.build_database`, without the Prefect flow around them, whose cost does not scale):

* strong scaling: the base workload (T, M) on 1 and on 2 workers: speedup = t1 / t2, efficiency =
  speedup / 2;
* weak scaling: the base workload on 1 worker against the doubled one (2T, 2M) on 2 workers:
  efficiency = t1 / t2 (1.0 is perfect).

All ratios come from one run of this script; issue 16 sets no goal for them, so ``"bars"`` records
the strong speedups and weak efficiencies without one (met None). Printed as JSON, with the per-chunk
figures (seconds per view and per material, bytes read and written) and a scheduler probe on 2 workers:
``--scheduler-tasks``
no-op tasks through the project's submit-and-wait loop (:func:`tasks.compute.run_all`), as many as the
view tasks of a 200-material ingest (seconds per task, scheduler memory per task).

Usage: ``python benchmarks/bench_scaling.py [--profile infra/slurm.yaml] [--device bonn-dome2] [--turntable 1]
[--materials 4] [--db-texture 64] [--repeats 3] [--keep DIR]``
With a Slurm profile and no Slurm controller answering (``sinfo``), it prints why and exits 0.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _measure import bar, log  # noqa: E402


def slurm_problem() -> str | None:
    """Why no Slurm controller can be used here, or None when ``sinfo`` answers."""
    if shutil.which("sinfo") is None:
        return "no sinfo on PATH (Slurm is not installed; .ci/run starts a one-node Slurm)"
    try:
        answer = subprocess.run(["sinfo", "-h"], capture_output=True, text=True, timeout=20)
    except subprocess.TimeoutExpired:
        return "sinfo did not answer within 20 s"
    return None if answer.returncode == 0 else f"sinfo failed: {answer.stderr.strip() or answer.returncode}"


def profile_with_workers(path: Path, n: int, folder: Path) -> Path:
    """A copy of the profile at ``path`` with ``n`` workers: Slurm/PBS ``minimum_jobs = maximum_jobs = n``
    (one worker per job in the shipped profile), local ``n_workers = n``."""
    data = yaml.safe_load(path.read_text())
    cluster = data["cluster"]
    if cluster.get("kind") in ("slurm", "pbs"):
        cluster.update(minimum_jobs=n, maximum_jobs=n)
    else:
        cluster["n_workers"] = n
    out = folder / f"{path.stem}-{n}.yaml"
    out.write_text(yaml.safe_dump(data))
    return out


def size_of(path: Path, skip: tuple[str, ...] = ()) -> int:
    """Bytes of every file under ``path`` (a store on disk), less the top-level folders in ``skip``."""
    return sum(p.stat().st_size for p in Path(path).rglob("*")
               if p.is_file() and p.relative_to(path).parts[0] not in skip)


def prepare(root: Path, device: str, turntable: int, materials: int, texture: int | None,
            db_texture: int) -> dict[str, object]:
    """Simulate and ingest the benchmark's data on a threaded cluster (not timed)."""
    from distributed import Client, LocalCluster

    from tasks.ingest import ingest_capture
    from tasks.simulate import SimulationConfig, simulate_database

    data: dict[str, object] = {}
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False) as cluster, Client(cluster) as client:
        for name, positions in (("capture_1x", turntable), ("capture_2x", 2 * turntable)):
            config = SimulationConfig(device=device, n_materials=1, seed=5, classes=("cloth",), n_turntable=positions,
                                      texture_size=texture)
            data[name] = simulate_database(config, root / name, client).stores[0]
        config = SimulationConfig(device="tiny", n_materials=2 * materials, seed=6, classes=("leather", "cloth"),
                                  n_turntable=1, texture_size=db_texture)
        stores = simulate_database(config, root / "db-captures", client).stores
        for i, capture in enumerate(sorted(stores)):
            btf = root / "db_2x" / Path(capture).name
            ingest_capture(capture, btf, client)
            if i < materials:               # the first M alternate leather, cloth: M/2 of each class
                shutil.copytree(btf, root / "db_1x" / btf.name)
    data.update(db_1x=root / "db_1x", db_2x=root / "db_2x")
    return data


def _scheduler_rss(dask_scheduler=None) -> int:
    import psutil

    return psutil.Process().memory_info().rss


def _noop(index: int, path: str) -> int:
    return index


def scheduler_probe(client, n_tasks: int) -> dict[str, float]:
    """What ``n_tasks`` tasks cost the scheduler through the project's one submit-and-wait loop
    (:func:`tasks.compute.run_all`), each with a path argument like a view task's: seconds from submit to
    the last result, and the scheduler process' resident memory before and at the peak (sampled)."""
    import threading

    from tasks.compute import run_all

    before = client.run_on_scheduler(_scheduler_rss)
    peak, done = [before], threading.Event()

    def sample() -> None:
        while not done.wait(0.5):
            peak.append(client.run_on_scheduler(_scheduler_rss))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    start = time.perf_counter()
    try:
        run_all(client, _noop, [(i, f"/data/btf/material-{i // 151:03d}.zarr") for i in range(n_tasks)])
    finally:
        done.set()
        sampler.join()
    seconds = time.perf_counter() - start
    return {"tasks": n_tasks, "seconds": round(seconds, 1), "ms_per_task": round(1000 * seconds / n_tasks, 3),
            "scheduler_rss_before": before, "scheduler_rss_peak": max(peak),
            "bytes_per_task": round((max(peak) - before) / n_tasks)}


def run_on(profile: Path, n: int, workloads: list[tuple[str, str, Path]], root: Path, settings,
           repeats: int, scheduler_tasks: int = 0) -> dict[str, object]:
    """Start the profile's cluster with ``n`` workers, then time each ``(command, label, input)`` ``repeats``
    times (the shortest counts: the machine is shared)."""
    from flows.profiles import load_profile
    from flows.runtime import dask_client
    from tasks.ingest import ingest_capture
    from tasks.model import build_database

    start = time.perf_counter()
    results: dict[str, object] = {}
    with dask_client(load_profile(profile)) as client:
        client.wait_for_workers(n, timeout=300)
        results["start_s"] = round(time.perf_counter() - start, 2)
        results["scheduler_rss_idle"] = client.run_on_scheduler(_scheduler_rss)
        log(f"{n} worker(s) ready after {results['start_s']} s: {sorted(client.scheduler_info()['workers'])}")
        for command, label, source in workloads:
            times = []
            for repeat in range(repeats):       # each into a new folder: nothing is reused
                out = root / f"out-{command}-{label}-{n}-{repeat}"
                t = time.perf_counter()
                if command == "ingest":
                    ingest_capture(str(source), out / "btf.zarr", client)
                    written = size_of(out / "btf.zarr")
                else:
                    summary = build_database(source, out, client, settings=settings)
                    written = size_of(out / "model.zarr")
                    assert len(summary["fits"]) == len(list(Path(source).glob("*.zarr")))
                times.append(time.perf_counter() - t)
                shutil.rmtree(out)
            # what the stage reads: a capture store's raw frames, not the simulator's ground truth (truth/)
            read = size_of(source, skip=("truth",)) if command == "ingest" else size_of(source)
            results[f"{command}_{label}"] = {"seconds": round(min(times), 2), "all_seconds": [round(x, 2) for x in times],
                                              "bytes_read": read, "bytes_written": written}
            log(f"{command} {label} on {n} worker(s): {', '.join(f'{x:.1f}' for x in times)} s")
        results["scheduler_rss_after"] = client.run_on_scheduler(_scheduler_rss)
        results["workers"] = len(client.scheduler_info()["workers"])
        if scheduler_tasks:
            results["scheduler_probe"] = scheduler_probe(client, scheduler_tasks)
            log(f"scheduler probe on {n} worker(s): {results['scheduler_probe']}")
    return results


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--profile", default=str(REPO / "infra" / "slurm.yaml"), help="execution profile")
    parser.add_argument("--device", default="bonn-dome2", help="dome of the ingest captures [bonn-dome2]")
    parser.add_argument("--turntable", type=int, default=1, help="turntable positions of the base capture [1]")
    parser.add_argument("--materials", type=int, default=4, help="materials of the base database (even) [4]")
    parser.add_argument("--texture", type=int, default=None, help="texture side of the ingest captures in px "
                        "[the device's]")
    parser.add_argument("--db-texture", type=int, default=64, help="texture side of the database in px [64]")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of each workload; the shortest counts [3]")
    parser.add_argument("--scheduler-tasks", type=int, default=30200,
                        help="no-op tasks of the scheduler probe on 2 workers: the view tasks of a 200-material "
                             "ingest of 151 views each [30200; 0: no probe]")
    parser.add_argument("--keep", default=None, help="keep the data in this folder (and reuse it when prepared "
                        "there with the same options)")
    args = parser.parse_args()
    profile = Path(args.profile).resolve()
    kind = yaml.safe_load(profile.read_text())["cluster"].get("kind", "local")
    if kind == "slurm":
        problem = slurm_problem()
        if problem:
            print(json.dumps({"benchmark": "scaling", "skipped": f"no Slurm: {problem}", "bars": []}), flush=True)
            print(f"bench_scaling: skipped: {problem}", file=sys.stderr)
            return 0
    from tasks.model import ModelSettings, with_k

    # the thesis' k capped by the tiny data, as `btf build-db` chooses them; fewer ALS iterations keep it short
    settings = with_k(ModelSettings(als_iterations=5), als=16)
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench-scaling-"))
    root.mkdir(parents=True, exist_ok=True)
    try:
        recipe = {k: getattr(args, k) for k in ("device", "turntable", "materials", "texture", "db_texture")}
        marker = root / "prepared.json"
        if marker.is_file() and json.loads(marker.read_text())["recipe"] == recipe:
            log(f"reusing the data in {root}")
            data = {k: Path(v) for k, v in json.loads(marker.read_text())["data"].items()}
        else:
            log(f"preparing data in {root}")
            data = prepare(root, args.device, args.turntable, args.materials, args.texture, args.db_texture)
            marker.write_text(json.dumps({"recipe": recipe, "data": {k: str(v) for k, v in data.items()}}))
        load_before = os.getloadavg()[0]
        per_n = {}
        base = [("ingest", "1x", data["capture_1x"]), ("build-db", "1x", data["db_1x"])]
        double = [("ingest", "2x", data["capture_2x"]), ("build-db", "2x", data["db_2x"])]
        per_n[1] = run_on(profile_with_workers(profile, 1, root), 1, base, root, settings, args.repeats)
        per_n[2] = run_on(profile_with_workers(profile, 2, root), 2, base + double, root, settings, args.repeats,
                          args.scheduler_tasks)
        ratios = {}
        for command in ("ingest", "build-db"):
            t1, t2 = per_n[1][f"{command}_1x"]["seconds"], per_n[2][f"{command}_1x"]["seconds"]
            t2w = per_n[2][f"{command}_2x"]["seconds"]
            ratios[command] = {"strong_speedup": round(t1 / t2, 2), "strong_efficiency": round(t1 / t2 / 2, 2),
                               "weak_efficiency": round(t1 / t2w, 2)}
        from btfcore.dome import get_device

        views = get_device(args.device).n_cam * args.turntable
        per_chunk = {
            "ingest_s_per_view_1_worker": round(per_n[1]["ingest_1x"]["seconds"] / views, 3),
            "ingest_bytes_read_per_view": per_n[1]["ingest_1x"]["bytes_read"] // views,
            "ingest_bytes_written_per_view": per_n[1]["ingest_1x"]["bytes_written"] // views,
            "build_db_s_per_material_1_worker": round(per_n[1]["build-db_1x"]["seconds"] / args.materials, 3),
            "build_db_bytes_read_per_material": per_n[1]["build-db_1x"]["bytes_read"] // args.materials,
            "model_bytes_written_per_material": per_n[1]["build-db_1x"]["bytes_written"] // args.materials,
        }
        print(json.dumps({
            "benchmark": "scaling", "profile": str(profile), "kind": kind, "machine": platform.node(),
            "cpus": os.cpu_count(), "load_1min_before": round(load_before, 2),
            "load_1min_after": round(os.getloadavg()[0], 2),
            "workload": {"device": args.device, "ingest_views_1x": views, "ingest_views_2x": 2 * views, "texture": args.texture,
                         "db_texture": args.db_texture, "repeats": args.repeats,
                         "materials_1x": args.materials, "materials_2x": 2 * args.materials,
                         "tasks": {"ingest": "one per view", "build-db": "two per material (bases, leave-one-out)"}},
            "ratios": ratios, "per_chunk": per_chunk, "runs": per_n,
            "bars": [bar(f"{command} {name.replace('_', ' ')} on 2 workers", value, "none (recorded)", None, 16)
                     for command, figures in ratios.items() for name, value in figures.items()
                     if name != "strong_efficiency"],
        }, indent=2, default=str))
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
