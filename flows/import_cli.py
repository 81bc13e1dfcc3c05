"""``btf import-raw`` and ``btf import-images``: the dome calibration, the checks before start-up, the
flow calls and their bracket warnings (kept out of :mod:`flows.cli`, which wires the commands)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

#: ``btf import-images --help``'s description.
IMPORT_IMAGES_DESCRIPTION = (
    "Read a folder of exposure brackets of 8- or 16-bit TIFF, PNG or JPEG images (OpenCV) and write a capture "
    "store holding the codes and each camera's response, calibrated from its brackets (Debevec & Malik or "
    "Robertson et al.) or read from --response; btf ingest merges through it. The manifest is import-raw's "
    "(times missing from it are read from EXIF); every problem is listed before any work starts. Brackets "
    "whose frames do not scale with their exposure times are flagged (--strict-brackets: refused).")


def dome_calibration(args: argparse.Namespace):
    """The :class:`btfcore.dome.Device` of ``--calibration FILE`` or ``--device NAME``."""
    from btfcore.dome import Device, get_device

    if args.calibration:
        try:
            return Device.from_json(json.loads(Path(args.calibration).read_text()))
        except (OSError, ValueError, KeyError, TypeError) as exc:  # ValueError: bad JSON, NaN/Inf, bad geometry
            raise ValueError(f"{args.calibration}: not a valid dome calibration ({exc}); fix the file or "
                             "write it again with Device.to_json") from None
    if not args.device:
        raise ValueError("give the dome calibration: --device NAME or --calibration FILE.json")
    return get_device(args.device)


def prepare_import_raw(args: argparse.Namespace, prepared: dict) -> None:
    """``btf import-raw``'s checks before start-up: the calibration, manifest and files, the output."""
    from tasks.ingest_raw import plan_raw_import, raw_import_metadata
    from tasks.staging import refuse_inputs_as_outputs
    from tasks.stores import check_capture_target

    prepared["device"] = dome_calibration(args)
    prepared["plan"] = plan_raw_import(args.folder, args.manifest)   # every problem listed at once
    refuse_inputs_as_outputs({"--out": args.out}, {f"raw file {p.name}": p for p in prepared["plan"].files.values()})
    meta = raw_import_metadata(prepared["plan"], prepared["device"])
    if not args.overwrite:
        check_capture_target(args.out, meta)


def prepare_import_images(args: argparse.Namespace, prepared: dict) -> None:
    """``btf import-images``' checks before start-up: the calibration, manifest and images, a response
    file, the output."""
    from tasks.ingest_images import image_import_metadata, load_response, plan_image_import, response_key
    from tasks.staging import refuse_inputs_as_outputs
    from tasks.stores import check_capture_target

    prepared["device"] = dome_calibration(args)
    prepared["plan"] = plan_image_import(args.folder, args.manifest)   # every problem listed at once
    if args.response is not None:
        load_response(args.response, int(prepared["plan"].white_level) + 1)   # a bad file refused before start-up
    refuse_inputs_as_outputs({"--out": args.out}, {f"image {p.name}": p for p in prepared["plan"].files.values()})
    meta = image_import_metadata(prepared["plan"], prepared["device"],
                                 response_key(args.response_method, args.response))
    if not args.overwrite:
        check_capture_target(args.out, meta)


def bracket_warnings(command: str, summary: dict) -> dict:
    """A stderr WARNING line per bracket whose frames do not scale with their exposure times."""
    from tasks.ingest_raw import bracket_flag_text

    for flag in summary.get("bracket_warnings", []):
        print(f"btf {command}: WARNING: {bracket_flag_text(flag)}", file=sys.stderr)
    return summary


def import_raw_cli_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    """``btf import-raw``'s flow with the parsed arguments; its JSON summary."""
    from flows.ingest import import_raw_flow

    return bracket_warnings("import-raw", import_raw_flow(
        args.folder, args.manifest, prepared["device"], args.out, address, overwrite=args.overwrite,
        plan=prepared["plan"], strict_brackets=args.strict_brackets))


def import_images_cli_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    """``btf import-images``' flow with the parsed arguments; its JSON summary."""
    from flows.ingest import import_images_flow

    return bracket_warnings("import-images", import_images_flow(
        args.folder, args.manifest, prepared["device"], args.out, address, prepared["plan"],
        overwrite=args.overwrite, method=args.response_method, response=args.response,
        strict_brackets=args.strict_brackets))
