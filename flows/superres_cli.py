"""``btf superres train|apply`` and ``btf evaluate superres``: the arguments and runs (entries of
:data:`flows.cli.COMMANDS`; docs/super-resolution.md).

``train`` is one small sequential job and runs in this process with torch's threads (no cluster);
``apply`` runs its flow on the execution profile's Dask cluster, one task per view.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from flows.acquisition_cli import _positive_int

SUPERRES_HELP = """\
Super-resolution of a BTF (SR paper: the thesis' fifth paper). The network (ESPCN
with a skip connection and batch norm, SR paper §4) up-samples each image's HDR
radiance region of interest by 2 before rectification; the regions come from
`btf ingest --keep-roi`.

  btf superres train BTF [BTF ...] --out MODEL.pt   learn from the stores' own regions,
        down-sampled once (--protocol exact: 1/2 -> 1) or twice (paper: 1/4 -> 1/2),
        118 rows of each store, the paper's images per material (or --fraction);
        Adam at 1e-2, MSE, early stopping.
  btf superres apply BTF --model MODEL.pt --out BTF2X   up-sample every region (one task
        per view; CUDA when present) and rectify it at twice the texture size into a
        btf-texture store; resumable; --method bicubic needs no model.

`btf resample` then brings BTF2X to a common angular sampling, as for any ingested store.
"""


def add_superres_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf superres``."""
    p.add_argument("action", choices=("train", "apply"), help="train a model or apply one")
    p.add_argument("btf", nargs="+", metavar="BTF",
                   help="BTF store(s) from `btf ingest --keep-roi` (apply: exactly one)")
    p.add_argument("--out", required=True, metavar="PATH", help="train: the model file (.pt); apply: the 2x BTF store")
    p.add_argument("--model", default=None, metavar="MODEL.pt", help="apply: model file of `btf superres train`")
    p.add_argument("--method", default="espcn", choices=("espcn", "bicubic"),
                   help="apply: espcn (the network) or bicubic interpolation of the regions [default: espcn]")
    p.add_argument("--overwrite", action="store_true",
                   help="apply: replace another store at --out (built beside it, swapped in when complete)")
    p.add_argument("--protocol", default="exact", choices=("exact", "paper"),
                   help="train: exact learns 1/2 -> 1 to apply 1 -> 2; paper learns 1/4 -> 1/2 (SR paper §5.1) "
                        "[default: exact]")
    p.add_argument("--fraction", type=float, default=None, metavar="F",
                   help="train: share of each store's rows whose regions give patches [default: 118 rows, the SR "
                        "paper's images per material]")
    p.add_argument("--normalisation", default=None, choices=("log", "scale"),
                   help="train: HDR input normalisation [default: the measured better one, docs/super-resolution.md]")
    p.add_argument("--epochs", type=_positive_int, default=None, metavar="N", help="train: most epochs")
    p.add_argument("--seed", type=int, default=0, help="train: seed of the rows, the split and the weights [default: 0]")


def superres_on_cluster(args: argparse.Namespace) -> bool:
    """``apply`` runs on the cluster; ``train`` in this process."""
    return args.action == "apply"


def prepare_superres(args: argparse.Namespace, prepared: dict) -> None:
    """``btf superres apply``'s checks before the cluster starts (source regions, model, ``--out``)."""
    from tasks.superres import check_apply

    if len(args.btf) != 1:
        raise ValueError(f"btf superres apply takes one BTF store, got {len(args.btf)}")
    check_apply(args.btf[0], args.model, args.out, method=args.method, overwrite=args.overwrite)


def superres_apply_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict[str, Any]:
    from flows.superres import superres_apply_flow as apply_flow

    return {"command": "superres apply", **apply_flow(args.btf[0], args.model, args.out, address, method=args.method,
                                                     overwrite=args.overwrite, progress=not args.no_progress)}


def run_superres_train(args: argparse.Namespace) -> int:
    """``btf superres train``: train in this process, print the summary."""
    from btfcore.superres.espcn import EspcnConfig
    from btfcore.superres.training import TrainingSettings
    from flows.superres import epoch_lines
    from tasks.superres import train_model

    if args.model or args.method != "espcn" or args.overwrite:
        raise ValueError("--model, --method and --overwrite belong to `btf superres apply`; drop them")
    if args.fraction is not None and not 0 < args.fraction <= 1:
        raise ValueError(f"--fraction {args.fraction}: give a share in (0, 1]")
    config = EspcnConfig() if args.normalisation is None else EspcnConfig(normalisation=args.normalisation)
    settings = TrainingSettings(seed=args.seed, **({"max_epochs": args.epochs} if args.epochs else {}))
    summary = train_model(args.btf, args.out, protocol=args.protocol, fraction=args.fraction, config=config,
                          settings=settings, progress=epoch_lines("btf superres train", not args.no_progress))
    brief = {k: v for k, v in summary.items() if k not in ("history", "stores")}
    print(json.dumps({"command": "superres train", **brief, "epochs": len(summary["history"])}, indent=2,
                     default=str))
    return 0


def add_evaluate_superres_arguments(p: argparse.ArgumentParser) -> None:
    """The options ``btf evaluate superres`` adds to ``btf evaluate``."""
    p.add_argument("--sr-materials-per-class", type=_positive_int, default=5, metavar="N",
                   help="superres: leathers and cloths each: from 4, 2 train one network for the others and 1 "
                        "validates (chooses the normalisation and Dong's alpha), the rest are test materials; 2-3: 1 "
                        "validates; 1: it is the test material [default: 5]")
    p.add_argument("--sr-texture", type=_positive_int, default=96, metavar="PX",
                   help="superres: texture side (the 2x truth is twice it) [default: 96]")
    p.add_argument("--sr-camera-scale", type=_positive_int, default=2, metavar="F",
                   help="superres: cameras with F times the tiny dome's pixels (regions 72 F px) [default: 2]")
    p.add_argument("--sr-epochs", type=_positive_int, default=20, metavar="N", help="superres: most epochs [default: 20]")


def superres_evaluation_config(args: argparse.Namespace) -> Any:
    """``btf evaluate superres``'s :class:`tasks.evaluate_superres.SuperresEvaluationConfig` (bad input raises)."""
    from tasks.evaluate_superres import SuperresEvaluationConfig

    if not args.out:
        raise ValueError("give --out DIR")
    m = args.sr_materials_per_class
    n_train, n_validation = (2, 1) if m >= 4 else (0, 1) if m >= 2 else (0, 0)
    return SuperresEvaluationConfig(materials_per_class=m, n_train=n_train, n_validation=n_validation,
                                    texture_size=args.sr_texture, camera_scale=args.sr_camera_scale,
                                    max_epochs=args.sr_epochs, seed=args.eval_seed)


def evaluate_superres_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict[str, Any]:
    from flows.superres import evaluate_superres_flow as flow

    summary = flow(args.out, address, prepared["config"], progress=not args.no_progress)
    out = Path(args.out).resolve()
    return {"command": "evaluate superres", "normalisation": summary["normalisation"],
            "verdicts": summary.get("verdicts"), "report_json": str(out / "report.json"),
            "report_html": str(out / "report.html")}
