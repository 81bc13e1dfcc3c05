"""``btf import-btf`` and ``btf export``: the Bonn BTF files (DFMF, FMF, BDI, PVF) in and out of btf-texture
stores (entries of :data:`flows.cli.COMMANDS`; docs/bonn-formats.md).

``import-btf`` streams a file into a store on the execution profile's Dask cluster (the Prefect flow of
:mod:`flows.import_btf`), after :func:`tasks.bonn.import_btf.check_import` read and checked the file's headers
in this process, before the cluster starts. ``export`` runs in this process without a cluster: it checks
everything (:func:`tasks.bonn.export_btf.check_export`) before it writes.

Nothing slow is imported at module level: ``btf --help`` builds these parsers' arguments only when the
command parses.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

IMPORT_HELP = """\
Import a Bonn BTF file into a btf-texture store. Formats, recognised by their
signature: DFMF (!DFMF08FCR, per-channel factorisation with a colour model:
0 RGB, 1 YUV, 9-12 log variants, ...), FMF (!FMF06FC[R], !FMF12FCER with
dynamic-range reduction and height map), BDI (!BDIF06R2!, raw, bzip2 or
sparse chunks with an ABRDF mask) and PVF (!PVF06FC[R]).

The file is streamed with bounded memory: Dask tasks decode groups of views x
bands of texture rows from memory maps of the file, never the whole BTF. The store holds linear RGB
textures, rows view-major and light fastest (file row l + n_l * v), texel
(x, y) at texture[y, x]; the directions of every row in the sample frame
(from the file's (theta, phi) radians); attributes for the angular sampling,
texture size, colour model, cosine flag, XML metadata, rotations, the source
file and its SHA-256 (docs/bonn-formats.md, "Importing"). Values are kept as
the file holds them (the cosine flag is recorded, not divided out).

Every header is checked against the file's size before the cluster starts: a
truncated or malformed file is refused with its byte offset and field.
--class and --material-id make the store a material of a `btf build-db`
database; `btf resample`, `btf render` and `btf reconstruct` take it like an
ingested store.
"""

EXPORT_HELP = """\
Export a finished btf-texture store (from `btf resample`, `btf import-btf`,
`btf ingest` or `btf reconstruct`) as a Bonn BTF file that btflib, btf.hh
(btf-extractor), pysmtb and the Mitsuba BTF plugin read. The store's rows must
form views x lights with the same number of lights in every view (an ingested
store's views are its turntable x camera positions, each with its own light
directions).

  --format dfmf   per-channel factorisation U . (S V^T) in a colour model
                  (--colour-model: 0 RGB, 1 YUV, 9 logY U V, 10 logY log|U|
                  log|V|, 11 logY U/Y V/Y, 12 log RGB, ...; btf.hh decodes
                  only 0 and 11)
  --format fmf    one factorisation of all channels (!FMF12FCER), RGB
  --format bdi    the textures themselves as half floats in chunks of scan
                  lines (--compression raw|bzip2|sparse), streamed from the
                  store band by band with bounded memory

--components K keeps K components per factorisation; the default, all of them
(min(rows, texels)), is lossless up to --precision (half: about 3 significant
digits relative to a texel's ABRDF norm; single: 7), at a file size of about
(rows + texels) x K scalars per channel. DFMF and FMF factorise in memory and
refuse stores over 256 MiB of float32 textures (use BDI for those).

Half floats hold at most 65504: a store of `btf ingest` without a radiometric
calibration holds DN/s, far more. --scale auto then writes the values times
the power of two that makes them fit (1 when they already do); the factor is
recorded in the file's XML (scale="..."), readers do not divide it out.
--precision single needs no scale (DFMF, FMF).

--basis MODEL_DIR --class CLS writes a DFMF on a model basis instead of the
store's own SVD: U is the class' ALS basis of linear RGB (from `btf build-db`,
its first --components vectors), shared by the channels, and S V^T the store
projected on it; the error summary says what the projection loses.

Kept: the directions (as (theta, phi) radians per view), the texture size, the
channel names; an imported store's meta block, XML and rotations are passed
through. The cosine flag is set for this project's stores: they hold measured
radiance, which includes the cosine of the light's polar angle. The file is
written beside --out (OUT.partial) and renamed into place when complete; an
existing file is replaced only with --overwrite. Needs no cluster.
"""


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} is not positive")
    return value


def add_import_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf import-btf``."""
    p.add_argument("file", metavar="FILE", help="a Bonn BTF file (.btf, .bdi, .fmf, .pvf)")
    p.add_argument("--out", required=True, metavar="STORE", help="the btf-texture store to write (.zarr)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a store of another file at --out (built beside it, swapped in when complete)")
    p.add_argument("--class", dest="material_class", default=None, metavar="CLASS",
                   help="material class recorded in the store, for `btf build-db` [default: none]")
    p.add_argument("--material-id", default=None, metavar="ID",
                   help="material id recorded in the store [default: the file's stem]")


def add_export_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf export``."""
    p.add_argument("store", metavar="STORE", help="a finished btf-texture store")
    p.add_argument("--format", required=True, choices=("dfmf", "fmf", "bdi"), help="file format (see above)")
    p.add_argument("--out", required=True, metavar="FILE", help="the file to write")
    p.add_argument("--precision", default="half", choices=("half", "single"),
                   help="DFMF/FMF scalars: half (2 bytes, what the public files use) or single [default: half]")
    p.add_argument("--colour-model", type=int, default=0, metavar="N",
                   help="DFMF colour model (0 RGB, 1 YUV, 9-12 log variants; docs/bonn-formats.md) [default: 0]")
    p.add_argument("--components", type=_positive_int, default=None, metavar="K",
                   help="DFMF/FMF components per factorisation [default: all, lossless up to --precision]")
    p.add_argument("--compression", default="raw", choices=("raw", "bzip2", "sparse"),
                   help="BDI chunk compression [default: raw]")
    p.add_argument("--lines-per-chunk", type=_positive_int, default=4, metavar="N",
                   help="BDI scan lines per chunk [default: 4, what Bonn's writers use]")
    p.add_argument("--scale", default="1", metavar="F|auto",
                   help="write the values times F (recorded in the file's XML); auto: 1 when the values fit half "
                        "floats, else the power of two that makes them fit [default: 1]")
    p.add_argument("--basis", default=None, metavar="MODEL_DIR",
                   help="DFMF on a model basis: U is the ALS basis of --class in this `btf build-db` folder, S V^T "
                        "the store projected on it (lossy; the store's rows must be the model's)")
    p.add_argument("--class", dest="basis_class", default=None, metavar="CLS", help="the class of --basis")
    p.add_argument("--overwrite", action="store_true", help="replace an existing file at --out")


def prepare_import(args: argparse.Namespace, prepared: dict) -> None:
    """``btf import-btf``'s checks before the cluster starts: the file's headers against its size, --out."""
    from tasks.bonn.import_btf import check_import

    prepared["check"] = check_import(args.file, args.out, args.overwrite)


def import_btf_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict[str, Any]:
    """``btf import-btf`` on the cluster at ``address``: the summary of :func:`flows.import_btf.import_btf_flow`."""
    from flows.import_btf import import_btf_flow as flow

    return {"command": "import-btf", **flow(args.file, args.out, address, overwrite=args.overwrite,
                                             material_class=args.material_class, material_id=args.material_id,
                                             progress=not args.no_progress)}


def run_export(args: argparse.Namespace) -> int:
    """``btf export`` in this process: check, write, print the summary as JSON."""
    from tasks.bonn.export_btf import export_store

    summary = export_store(args.store, args.out, format=args.format, precision=args.precision,
                           colour_model=args.colour_model, components=args.components,
                           compression=args.compression, overwrite=args.overwrite,
                           lines_per_chunk=args.lines_per_chunk, scale=args.scale, basis=args.basis,
                           basis_class=args.basis_class)
    print(json.dumps(summary, indent=2))
    return 0
