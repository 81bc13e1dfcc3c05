"""The arguments of the ``btf`` subcommands (entries of :data:`flows.cli.COMMANDS`) and the global options.

A subcommand's arguments are added only when that subcommand parses (:class:`flows.cli.CommandParser`),
so building the parser imports nothing slow: ``btf --help`` and the first line of a computing command
come before numpy, scipy, Dask or Prefect are imported. Those of ``btf sample``, ``btf plan`` and
``btf render`` are in :mod:`flows.acquisition_cli`.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

#: Levels of ``--log-level`` (Prefect's and Dask's loggers).
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


def add_global_options(p: argparse.ArgumentParser, after_command: bool = False) -> None:
    """The options of ``btf`` itself, given before the subcommand or (``after_command``) after it.

    After the subcommand they are in a group of their own and have no default (``argparse.SUPPRESS``):
    one given there sets the value, one not given leaves the value from before the subcommand.
    """
    group = p.add_argument_group("global options (also accepted before the command)") if after_command else p
    unset = {"default": argparse.SUPPRESS} if after_command else {}
    group.add_argument("--cluster", metavar="PROFILE", **({"default": None} | unset),
                       help="execution profile YAML (cluster kind, workers, memory, Prefect API) "
                            "[default: $BTF_CLUSTER_CONFIG or infra/local.yaml]")
    group.add_argument("--no-progress", action="store_true", **unset,
                       help="no progress display (bars in a terminal, timestamped lines elsewhere)")
    group.add_argument("--quiet", "-q", action="store_true", **unset,
                       help="only errors and the final JSON: no progress, no info lines, library logs at ERROR")
    group.add_argument("--verbose", "-v", action="store_true", **unset,
                       help="also show Prefect's and Dask's info logs (same as --log-level INFO)")
    group.add_argument("--log-level", choices=LOG_LEVELS, type=str.upper, metavar="LEVEL", **unset,
                       help=f"level of Prefect's and Dask's logs: {', '.join(LOG_LEVELS)} [default: WARNING, or "
                            "$PREFECT_LOGGING_LEVEL and $DASK_LOGGING__DISTRIBUTED]")


class _Deferred:
    """A part of a help text computed only when the help is shown (``%(name)s``), not when parsing."""

    def __init__(self, text: Callable[[], str]):
        self.text = text

    def __str__(self) -> str:
        return self.text()


def _material_classes() -> str:
    from btfcore.simulate.materials import MATERIAL_CLASSES   # imports scipy and scikit-image

    return ", ".join(MATERIAL_CLASSES)


def _add_simulation_options(p: argparse.ArgumentParser) -> None:
    from btfcore.dome import BAYER_PATTERNS, DEVICE_NAMES

    p.add_argument("--device", default="tiny", choices=DEVICE_NAMES,
                   help="dome preset: tiny (tests, seconds), bonn-dome2 (11 cameras x 198 LEDs x 12 "
                        "turntable positions = 26,136 pairs), ubo-dome1 (151 x 151) [default: tiny]")
    materials = p.add_argument("--materials", type=int, default=6, metavar="N",
                               help="number of materials; classes cycle through %(classes)s [default: 6]")
    materials.classes = _Deferred(_material_classes)
    p.add_argument("--seed", type=int, default=0, help="root seed of materials and noise [default: 0]")
    p.add_argument("--illumination", default="single", choices=("single", "multiplexed", "both"),
                   help="single-LED patterns, S-matrix multiplexed patterns, or both [default: single]")
    p.add_argument("--classes", default=None, metavar="A,B,...",
                   help="comma-separated material classes to cycle through; 'white-standard' simulates the "
                        "flat white target of a radiometric calibration [default: the six material classes]")
    p.add_argument("--bayer", default=None, choices=BAYER_PATTERNS,
                   help="override the device's Bayer layout")
    p.add_argument("--texture-size", type=int, default=None, metavar="PX",
                   help="override the rectified texture side (ground truth is also written at 2x)")
    p.add_argument("--turntable", type=int, default=None, metavar="N",
                   help="simulate only the first N turntable positions (a pruned run)")
    p.add_argument("--psf-sigma", type=float, default=0.0, metavar="PX",
                   help="Gaussian point spread function of the cameras, sigma in raw pixels [default: 0, off]")
    p.add_argument("--camera-scale", type=int, default=1, metavar="N",
                   help="cameras with N times the dome's pixels along each axis (a pixel of the dome's camera is "
                        "an N x N block): a larger region of interest, for the super-resolution evaluation "
                        "[default: 1]")
    p.add_argument("--non-ideal", default=None, metavar="PRESET[,FIELD=VALUE...]",
                   help="a dome that is not ideal: 'realistic' (VMV §5.1's 10 dB single-light / 0 dB multiplexed "
                        "gains and one bracket per multiplexed capture, 1 %% LED drift per shot, 0.1 px registration "
                        "error, 1e-4 hot pixels) and/or FIELD=VALUE overrides, e.g. realistic,led_drift=0.02 "
                        "(docs/simulator-physics.md, \"A dome that is not ideal\") [default: the ideal dome]")


def simulate(p: argparse.ArgumentParser) -> None:
    """The options of ``btf simulate``: the simulation's and the output's."""
    _add_simulation_options(p)
    p.add_argument("--out", required=True, metavar="PATH", help="output folder of the database")
    p.add_argument("--overwrite", action="store_true", help="replace finished stores of another config")
    p.add_argument("--plan", default=None, metavar="PLAN.json",
                   help="execute an acquisition plan (`btf plan` JSON or CSV): per turntable position its shots "
                        "(LEDs on, cameras, shutter brackets) instead of --illumination and automatic brackets; "
                        "`btf ingest` then writes a BTF store (full sets) or a measurement store "
                        "(docs/measurement-store.md)")


def demo(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf demo``."""
    p.add_argument("--out", default="demo-output", metavar="DIR", help="output folder [default: demo-output]")
    p.add_argument("--seed", type=int, default=0, help="root seed [default: 0]")
    p.add_argument("--materials", type=int, default=12, metavar="N",
                   help="materials to simulate; the model database is built when there are at least two per "
                        "class [default: 12]")


def import_raw(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf import-raw``."""
    p.add_argument("folder", metavar="FOLDER", help="folder holding the raw files")
    p.add_argument("--manifest", required=True, metavar="FILE", help="CSV or JSON manifest")
    p.add_argument("--device", default=None, help="dome calibration preset (tiny, bonn-dome2, ubo-dome1)")
    p.add_argument("--calibration", default=None, metavar="JSON",
                   help="dome calibration file (Device.to_json layout); overrides --device")
    p.add_argument("--out", required=True, metavar="STORE", help="capture store to write (.zarr)")
    p.add_argument("--overwrite", action="store_true", help="replace a finished store at --out")
    _strict_brackets(p)


def _strict_brackets(p: argparse.ArgumentParser) -> None:
    p.add_argument("--strict-brackets", action="store_true",
                   help="fail on a bracket whose frames do not scale with their exposure times (default: a WARNING "
                        "line and the report's bracket_warnings)")


def import_images(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf import-images``."""
    import_raw(p)
    p.add_argument("--response-method", choices=("debevec", "robertson"), default="debevec",
                   help="camera response calibration and HDR merge: Debevec & Malik or Robertson et al. "
                        "[default: debevec]")
    p.add_argument("--response", default=None, metavar="FILE",
                   help="the camera's inverse response (.npy, .json or .csv/.txt: one row per code of 1 or 3 "
                        "numbers, R, G, B) instead of calibrating it from the brackets")


def ingest(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf ingest``."""
    p.add_argument("capture", metavar="CAPTURE", help="capture store (.zarr)")
    p.add_argument("--out", required=True, metavar="BTF", help="BTF store to write (.zarr)")
    add_calibration(p)
    p.add_argument("--overwrite", action="store_true",
                   help="recompute and replace the output at --out (kept until the new one is complete and checked)")
    p.add_argument("--keep-roi", action="store_true",
                   help="also keep each view's HDR radiance region of interest before rectification (array roi "
                        "and the views' homography in the BTF store), the input of super-resolution")


def resample(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf resample``."""
    p.add_argument("btf", metavar="BTF", help="finished BTF store from `btf ingest` (.zarr)")
    p.add_argument("--out", required=True, metavar="BTF2", help="resampled BTF store to write (.zarr)")
    p.add_argument("--sampling", default="ubo2014", metavar="ubo2014|FILE.json",
                   help='target directions: ubo2014 (151 lights x 151 views) or a JSON file {"light_dirs": '
                        '[[x, y, z], ...], "view_dirs": [[x, y, z], ...]} in the sample frame (z = surface '
                        'normal, z > 0; normalised here) [default: ubo2014]')
    p.add_argument("--overwrite", action="store_true", help="replace an output of another source or sampling")


def build_db(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf build-db``."""
    p.add_argument("db", metavar="DB", help="folder of ingested BTF stores (.zarr), one per material")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--classes", default=None, metavar="JSON",
                   help='material classes for stores that do not carry one: {"<store name>": "<class>", ...}')
    p.add_argument("--k-log-y", type=int, default=None, metavar="K",
                   help="per-material log Y basis vectors [default: the thesis' 200, capped by the data]")
    p.add_argument("--k-chroma", type=int, default=None, metavar="K",
                   help="per-material U/Y and V/Y basis vectors [default: 100, capped by the data]")
    p.add_argument("--k-merged", type=int, default=None, metavar="K",
                   help="basis vectors kept by each merge [default: 2048, capped by the data]")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a model store of another light/view sampling (or anything else) at OUT/model.zarr: "
                        "the new one is built beside it (model.partial.zarr) and put in place once complete")


def schedule(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf schedule``."""
    p.add_argument("what", choices=("build-db",), help="the job to schedule")
    p.add_argument("db", metavar="DB", help="folder of ingested BTF stores")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder of the model database")
    p.add_argument("--cron", required=True, metavar="EXPR", help='cron expression, e.g. "0 3 * * *" (03:00 daily)')
    p.add_argument("--name", default="build-db", help="deployment name [default: build-db]")
    p.add_argument("--classes", default=None, metavar="JSON", help="material classes for stores without one")


def deploy(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf deploy``."""
    p.add_argument("--file", default=None, metavar="YAML",
                   help="deployments to register (Prefect's prefect.yaml layout) [default: the repository's "
                        "prefect.yaml]")
    p.add_argument("--pool", default=None, metavar="NAME",
                   help="process work pool to register them on [default: each deployment's work_pool.name, "
                        "else btf]")
    p.add_argument("--name", action="append", default=None, metavar="DEPLOYMENT",
                   help="register only this deployment (repeatable) [default: all]")


def export_exr(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf export-exr``."""
    p.add_argument("btf", metavar="BTF", help="BTF store (.zarr)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--lv", default="all", metavar="ROWS",
                   help="rows to export: 'all' or a comma list of indices and ranges, e.g. 0,5,10-20 [default: all]")
    p.add_argument("--keep-nonfinite", action="store_true",
                   help="write textures with NaN or Inf texels as they are instead of refusing them")


def evaluate(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf evaluate``."""
    p.add_argument("what", choices=("ingest", "acquisition", "superres"),
                   help="ingest: a BTF store from `btf ingest` against its capture's truth; acquisition: leave-one-out "
                        "evaluation of sparse, multiplexed and sparse+multiplexed acquisition on a simulated truth "
                        "database (--db, --out; docs/evaluation.md); superres: bicubic, Dong et al. and the ESPCN "
                        "against the measured and the exact 2x truth on simulated leather and cloth (--out; "
                        "docs/super-resolution.md)")
    p.add_argument("--truth", default=None, metavar="SIM", help="ingest: simulated capture store (with truth/)")
    p.add_argument("--btf", default=None, metavar="BTF", help="ingest: BTF store from `btf ingest`")
    p.add_argument("--db", default=None, metavar="TRUTH_DB_DIR",
                   help="acquisition: folder of truth BTF stores; missing ones are rendered into it")
    p.add_argument("--out", default=None, metavar="DIR", help="acquisition: output folder (report.json, report.html)")
    p.add_argument("--eval-device", default="bonn-dome2", metavar="NAME",
                   help="acquisition: dome preset [default: bonn-dome2]")
    p.add_argument("--eval-turntable", type=int, default=2, metavar="N",
                   help="acquisition: first N turntable positions [default: 2, 4,356 light/view pairs]")
    p.add_argument("--eval-texture", type=int, default=32, metavar="PX", help="acquisition: texture side [default: 32]")
    p.add_argument("--eval-materials-per-class", type=int, default=2, metavar="N",
                   help="acquisition: materials per class (>= 2 for leave-one-out) [default: 2]")
    p.add_argument("--eval-seed", type=int, default=0, metavar="S", help="acquisition: root seed [default: 0]")
    p.add_argument("--eval-render", type=int, default=1, metavar="N",
                   help="acquisition: materials (one per class, structured classes first) whose reconstructions "
                        "are rendered and scored by rendering PSNR; each adds one reconstruction store per "
                        "strategy and its renderings [default: 1]")
    p.add_argument("--no-adaptive", action="store_true",
                   help="acquisition: skip the adaptive-capture loop on the held-out materials (docs/adaptive-capture.md; "
                        "about half of the run: 151 of 324 s at the default scale on 2 cores)")
    add_adaptive_choices(p, "--adaptive-", "acquisition: the adaptive loop's ")
    p.add_argument("--non-ideal", default=None, metavar="PRESET[,FIELD=VALUE...]",
                   help="acquisition: measure under a dome that is not ideal: 'realistic' (VMV §5.1's gains and "
                        "single exposure of the multiplexed captures, 1 %% LED drift, 0.1 px registration error, "
                        "1e-4 hot pixels) and/or FIELD=VALUE overrides (docs/simulator-physics.md, \"A dome that is "
                        "not ideal\") [default: the ideal dome]")
    p.add_argument("--report", default=None, metavar="PATH",
                   help="ingest: where to write the metrics [default: report.json]; acquisition and superres "
                        "write report.json and report.html into --out")
    from flows.superres_cli import add_evaluate_superres_arguments

    add_evaluate_superres_arguments(p)


def validate(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf validate``."""
    p.add_argument("stores", nargs="+", metavar="STORE",
                   help="capture, BTF, measurement or model store (.zarr; a `btf build-db` folder: its model.zarr)")
    p.add_argument("--allow-incomplete", action="store_true", help="accept stores whose run has not finished")
    p.add_argument("--deep", action="store_true",
                   help="read every chunk, verify its checksum and count the NaN and Inf values of float arrays "
                        "(reads the whole store, one chunk at a time)")


def reconstruct(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf reconstruct``."""
    p.add_argument("measurement", metavar="MEASUREMENT", help="measurement store or BTF store (.zarr)")
    p.add_argument("--model", required=True, metavar="MODEL_DIR", help="`btf build-db` output folder")
    p.add_argument("--class", dest="cls", required=True, metavar="CLS", help="material class whose basis is used")
    p.add_argument("--basis", default="als", choices=("als", "log_y", "abtf_log_y"),
                   help="als (linear RGB; any measurement), log_y or abtf_log_y (single-light only) [default: als]")
    p.add_argument("--method", default="pinv", choices=("pinv", "tikhonov", "direct", "projection", "thresholded"),
                   help="pinv/tikhonov: sparse single-light; direct: multiplexed (paper 4 eq. 10); projection/"
                        "thresholded: denoise a full demultiplexable measurement [default: pinv]")
    p.add_argument("--lam", type=float, default=None, metavar="L",
                   help="lambda of lambda*Sigma^-1 [default: tikhonov 0.01 for als, 40 for log bases (the thesis); "
                        "direct 0]")
    p.add_argument("--k", type=int, default=None, metavar="K", help="use only the first K basis vectors")
    p.add_argument("--out", required=True, metavar="BTF", help="BTF store to write (.zarr)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace another store at --out once the new one is complete")
    add_calibration(p, " (for a model of corrected BTFs; the measurement store itself is uncorrected: "
                             "single-light rows are corrected before the solve, multiplexed rows get one operator "
                             "per colour channel)")


def add_calibration(p: argparse.ArgumentParser, note: str = "") -> None:
    """``--white``, ``--white-albedo`` and ``--colour-matrix`` of ``btf ingest`` and ``btf reconstruct``."""
    p.add_argument("--white", default=None, metavar="WHITE_BTF",
                   help="radiometric correction: the uncorrected `btf ingest` output of a white-standard capture "
                        "on the same dome (simulate one with --classes white-standard); each LED's RGB gain is "
                        "measured on it and divided out, so the BTF is in the ground truth's unit" + note)
    p.add_argument("--white-albedo", type=float, default=0.99, metavar="A",
                   help="albedo of the white standard [default: 0.99]")
    p.add_argument("--colour-matrix", default=None, metavar="JSON",
                   help='camera colour matrix applied after the LED gains: {"matrix": [[...], [...], [...]]}, '
                        "3x3 or 3x4 (affine)")


def cluster(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf cluster``."""
    p.add_argument("action", choices=("spec",),
                   help="spec: print the cluster resource of a kubernetes profile as YAML (for kubectl apply -f -)")
    p.add_argument("profile", metavar="PROFILE", help="execution profile YAML of kind kubernetes "
                   "(example: infra/kubernetes.yaml)")


def add_adaptive_choices(p: argparse.ArgumentParser, prefix: str, what: str = "") -> None:
    """``PREFIXselect``, ``PREFIXrows`` and ``PREFIXpredictor`` of the adaptive loop (``btf acquire``: ``--``,
    ``btf evaluate``: ``--adaptive-``; docs/adaptive-capture.md)."""
    p.add_argument(f"{prefix}select", default="committee", choices=("committee", "posterior"),
                   help=f"{what}choice of the next shot: where a committee of the model database's other "
                        "materials' ALS bases disagrees with the class basis (the error a structure the class basis "
                        "lacks leaves), or the largest reduction of the class basis' posterior error "
                        "[default: committee]")
    p.add_argument(f"{prefix}rows", default="fused", choices=("fused", "model"),
                   help=f"{what}measured rows of the reconstruction (also the fixed samplings' it is compared "
                        "with): fused with the measurements, or the basis' fit only (paper 4 eq. 10) "
                        "[default: fused]")
    p.add_argument(f"{prefix}predictor", default="posterior", choices=("posterior", "cv", "probes"),
                   help=f"{what}error prediction the target (and the evaluation's bar 2) is tested on: the "
                        "posterior under the noise model and the start rows' misfit, the measured groups' "
                        "leave-one-group-out error, or probes: every 3rd shot after the start design is a group "
                        "drawn at random from one brightness quartile of the groups in turn, not chosen, and the "
                        "unmeasured rows' error is estimated from theirs by a regression on the committee's "
                        "disagreement with an intercept per quartile (needs --select committee). Probes made the "
                        "prediction at the budget's stop far more reliable on simulated materials, at a cost of "
                        "shots to a given error (docs/adaptive-capture.md, \"Probe groups\") [default: posterior]")
