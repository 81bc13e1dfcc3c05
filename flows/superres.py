"""Prefect flows of super-resolution (SR paper): ``btf superres apply`` and ``btf evaluate superres``
(``btf superres train`` runs in its own process, :mod:`flows.superres_cli`; its stage is reused here).

Wiring only: the numerics are :mod:`btfcore.superres`, the stores and model files
:mod:`tasks.superres`, the evaluation :mod:`tasks.evaluate_superres` (docs/super-resolution.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.runtime import RETRY_ONCE


def epoch_lines(name: str, enabled: bool):
    """``progress(epoch, record)`` of a training: one line per epoch (terminal or job log)."""
    from flows.progress import say

    def progress(epoch: int, record: Any) -> None:
        say(f"{name}: epoch {epoch}: training loss {record.train_loss:.4g}, validation loss "
            f"{record.validation_loss:.4g}, learning rate {record.learning_rate:.2g} ({record.seconds:.1f} s)",
            show=enabled)
    return progress


@task(name="superres-train", cache_policy=NO_CACHE)
def train_stage(stores: list[str], model: str, protocol: str, fraction: float | None, config: Any, settings: Any,
                progress: bool, name: str = "superres train") -> dict[str, Any]:
    """Train one network (in this process, with torch's threads); reuse a model file of the same training."""
    from tasks.superres import train_model

    return train_model(stores, model, protocol=protocol, fraction=fraction, config=config, settings=settings,
                       progress=epoch_lines(name, progress))


@task(name="superres-apply", **RETRY_ONCE, cache_policy=NO_CACHE)
def apply_stage(btf: str, model: str | None, out: str, method: str, scheduler_address: str, overwrite: bool,
                progress: bool) -> dict[str, Any]:
    from distributed import Client

    from flows.progress import progress_bar
    from tasks.superres import superres_apply

    bar, update = progress_bar(f"superres apply ({method})", progress, unit="view")
    with bar, Client(scheduler_address, set_as_default=False) as client:
        return superres_apply(btf, model, out, client, method=method, overwrite=overwrite, progress=update)


@flow(name="btf-superres-apply", log_prints=False)
def superres_apply_flow(btf: str, model: str | None, out: str, scheduler_address: str, method: str = "espcn",
                        overwrite: bool = False, progress: bool = True) -> dict[str, Any]:
    """Up-sample every region of ``btf`` (``btf ingest --keep-roi``) and rectify it at twice the texture
    size into the ``btf-texture`` store ``out``; resumable, staged with ``overwrite``."""
    return apply_stage(btf, model, out, method, scheduler_address, overwrite, progress)


@task(name="superres-simulate", **RETRY_ONCE, cache_policy=NO_CACHE)
def simulate_db_stage(config: Any, out_dir: str, scheduler_address: str, progress: bool) -> list[str]:
    """The evaluation's simulated leather and cloth captures (finished ones are reused)."""
    from distributed import Client

    from flows.progress import progress_bar
    from tasks.simulate import simulate_database

    bar, update = progress_bar(f"superres: simulate {config.n_materials} materials", progress, unit="view")
    with bar, Client(scheduler_address, set_as_default=False) as client:
        return simulate_database(config, out_dir, client, progress=update).stores


@task(name="superres-ingest", **RETRY_ONCE, cache_policy=NO_CACHE)
def ingest_regions_stage(stores: list[str], out_dir: str, scheduler_address: str, progress: bool) -> list[str]:
    """Ingest every capture with its regions of interest (``--keep-roi``); finished ones are reused."""
    from distributed import Client

    from flows.progress import in_parts, progress_bar
    from tasks.ingest import ingest_capture
    from tasks.stores import open_capture_store

    captures = [open_capture_store(store) for store in stores]
    bar, update = progress_bar("superres: ingest with regions", progress, unit="view")
    outs = [str(Path(out_dir) / Path(store).name) for store in stores]
    with bar, Client(scheduler_address, set_as_default=False) as client:
        for capture, out, part in zip(captures, outs, in_parts(update, [c.n_views for c in captures])):
            ingest_capture(capture, out, client, keep_roi=True, progress=part)
    return outs


@task(name="superres-score", **RETRY_ONCE, cache_policy=NO_CACHE)
def score_stage(kind: str, args: list[tuple], scheduler_address: str, progress: bool) -> list[dict[str, Any]]:
    """One Dask task per material: ``kind`` ``"validation"`` or ``"test"`` (:mod:`tasks.evaluate_superres`)."""
    from distributed import Client

    from flows.progress import progress_bar
    from tasks.compute import run_all
    from tasks.evaluate_superres import test_material, validation_material

    fn = validation_material if kind == "validation" else test_material
    if not args:                                     # no such materials (the demo validates none): no display
        return []
    bar, update = progress_bar(f"superres: {kind} materials", progress, unit="material")
    with bar, Client(scheduler_address, set_as_default=False) as client:
        return run_all(client, fn, args, update)


@task(name="superres-report", cache_policy=NO_CACHE)
def report_stage(out: str, summary: dict[str, Any]) -> dict[str, str]:
    from tasks.superres_report import write_superres_report

    return write_superres_report(out, summary)


@flow(name="btf-evaluate-superres", log_prints=False)
def evaluate_superres_flow(out: str, scheduler_address: str, config: Any = None, progress: bool = True,
                           captures: list[str] | None = None) -> dict[str, Any]:
    """The SR paper's Table 2 on simulated leather and cloth (:mod:`tasks.evaluate_superres`): simulate,
    ingest with regions, choose the normalisation and Dong's alpha on the validation materials (each training
    its own networks), train one network on the training materials, score the test materials (each with its
    own networks, and the training materials' one), render, report. Reruns reuse every finished store and
    model file. ``captures``: simulated leather and cloth capture stores of ``config``'s dome to use instead
    of simulating them (the demo passes its own)."""
    import time

    from btfcore.superres.espcn import EspcnConfig
    from btfcore.superres.training import TrainingSettings
    from tasks.evaluate_superres import SuperresEvaluationConfig, choose, model_path
    from tasks.superres import PAPER_IMAGES, with_regions

    start = time.perf_counter()
    config = config or SuperresEvaluationConfig()
    sim = config.simulation()
    if captures is None:
        captures = simulate_db_stage(sim, str(Path(out) / "db"), scheduler_address, progress)
    btfs = ingest_regions_stage(captures, str(Path(out) / "btf"), scheduler_address, progress)
    split = config.split([Path(p).stem for p in btfs])
    by_name = {Path(p).stem: p for p in btfs}
    capture_of = {Path(p).stem: p for p in captures}
    models_dir = str(Path(out) / "models")
    validation = score_stage("validation", [(by_name[n], list(config.dong_alphas), config.dong_rank, models_dir,
                                             config.training()) for n in split["validation"]],
                             scheduler_address, progress)
    normalisation, alpha = choose(validation, default=EspcnConfig().normalisation)
    others = None
    if split["train"]:                            # the SR paper's split: one network for the other materials
        others = str(model_path(out, "others"))
        # the paper's 118 images in all, drawn evenly from the training materials (its §5.1 count per material
        # over 4 materials would train 4x longer than each material's own networks)
        share = config.fraction or PAPER_IMAGES / sum(with_regions(by_name[n]).n_lv for n in split["train"])
        trained = train_stage([by_name[n] for n in split["train"]], others, "exact", share,
                              EspcnConfig(normalisation=normalisation),
                              TrainingSettings(max_epochs=config.max_epochs, seed=config.seed), progress,
                              name=f"superres train (other materials, {normalisation})")
    device = sim.build_device().to_json()
    tests = score_stage("test", [(by_name[n], capture_of[n], others, normalisation, alpha, config.dong_rank, device,
                                  str(Path(out) / "figures"), models_dir, config.training())
                                 for n in split["test"]], scheduler_address, progress)
    first = tests[0]
    rendered = render_stage(by_name[first["material"]], first["models"][f"exact_{normalisation}"], out,
                            scheduler_address, progress)
    summary = {"report": "btf-evaluate-superres", "config": config.to_json(), "split": split,
               "normalisation": normalisation, "dong_alpha": alpha,
               "training_others": trained if others else None,
               "validation": dict(zip(split["validation"], validation)), "materials": tests,
               "rendering": rendered, "seconds": round(time.perf_counter() - start, 1)}
    return {**summary, **report_stage(out, summary)}


@task(name="superres-render", cache_policy=NO_CACHE)
def render_stage(btf: str, model: str, out: str, scheduler_address: str, progress: bool) -> dict[str, Any]:
    """``btf superres apply`` on one test material (the chunked stage itself) and renderings of the 1x and
    the super-resolved BTF on a sphere."""
    from distributed import Client

    from flows.progress import progress_bar
    from tasks.render import render_store
    from tasks.superres import superres_apply

    sr = str(Path(out) / "superres" / Path(btf).name)
    bar, update = progress_bar("superres apply (espcn)", progress, unit="view")
    with bar, Client(scheduler_address, set_as_default=False) as client:
        applied = superres_apply(btf, model, sr, client, progress=update)
    figures = Path(out) / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    images = []
    for label, store in (("1x (ingested)", btf), ("2x (ESPCN)", sr)):
        png = figures / f"render-{'sr' if store == sr else 'ingested'}.png"
        render_store(store, "sphere", out_png=png, image_size=256)
        images.append({"file": f"figures/{png.name}", "caption": f"{Path(btf).stem} on a sphere: {label}"})
    return {"store": sr, "apply": applied, "figures": images}
