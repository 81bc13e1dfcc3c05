"""Bonn BTF exchange formats: DFMF, FMF, PVF, BDI (docs/bonn-formats.md).

Readers return lazy views (``np.memmap``) into the file; every count a header claims is checked
against the file's size before anything is read or allocated, and a bad file raises
:class:`BonnFormatError` naming the file, the byte offset and the field.
"""

from tasks.bonn.dfmf import Factorised, read_factorised, rewrite, write_dfmf, write_fmf
from tasks.bonn.errors import BonnFormatError
from tasks.bonn.header import (SIGNATURES, ByteReader, CommonHeader, make_header, open_reader,
                               read_common_header, read_signature, write_common_header)
from tasks.bonn.pvf import Pvf, PvfSlot, read_pvf, rewrite_pvf, write_pvf

__all__ = ["SIGNATURES", "BonnFormatError", "ByteReader", "CommonHeader", "Factorised", "Pvf",
           "PvfSlot", "make_header", "open_reader", "read_common_header", "read_factorised",
           "read_pvf", "read_signature", "rewrite", "rewrite_pvf", "write_common_header",
           "write_dfmf", "write_fmf", "write_pvf"]
