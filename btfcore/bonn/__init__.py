"""Numerics of the Bonn BTF exchange formats (DFMF, FMF, BDI, PVF): colour models and factorisations.

Arrays in, arrays out: the byte layouts and the lazy file readers live in
:mod:`tasks.bonn`. docs/bonn-formats.md, "Colour models and decoding
(btfcore.bonn)", documents the formulas and their sources. Decoding a block of a
factorised file to linear RGB is::

    rgb = decode_colour(decode_textures(U, SxV, rows, texels), model, mean, matrix)

then :func:`restore_dynamic_range` when the FMF12 flag is set (btflib applies
the colour model first, then the dynamic-range restore, then the cosine division).
"""

from btfcore.bonn.colour_models import (
    COLOUR_MODELS,
    DRR_EPS,
    UnknownColourModelError,
    decode_colour,
    encode_colour,
    reduce_dynamic_range,
    restore_dynamic_range,
)
from btfcore.bonn.factorisation import decode_textures, factorise

__all__ = [
    "COLOUR_MODELS",
    "DRR_EPS",
    "UnknownColourModelError",
    "decode_colour",
    "decode_textures",
    "encode_colour",
    "factorise",
    "reduce_dynamic_range",
    "restore_dynamic_range",
]
