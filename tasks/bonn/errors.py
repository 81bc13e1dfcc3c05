"""The one error type of the Bonn format readers (docs/bonn-formats.md, "Malformed files")."""

from __future__ import annotations

import os


class BonnFormatError(ValueError):
    """A Bonn BTF file (DFMF, FMF, PVF, BDI) that does not parse.

    ``str(err)`` reads ``"<path>: byte <offset>, <field>: <message>; <fix>"``: the file, where in
    it (the byte offset of the field being read, ``?`` when it does not apply), which field, what
    is wrong and what to do about it.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    offset : int or None
        Byte offset of the field that is wrong (``None``: not tied to one place).
    field : str
        Name of the field, as in docs/bonn-formats.md (``"meta.size"``, ``"U[1]"``, ...).
    message : str
        What is wrong.
    fix : str
        What the user can do.
    """

    def __init__(self, path: str | os.PathLike, offset: int | None, field: str, message: str,
                 fix: str) -> None:
        self.path = os.fspath(path) if path is not None else "<unknown file>"
        self.offset = None if offset is None else int(offset)
        self.field = field
        self.message = message
        self.fix = fix
        super().__init__(self.path, self.offset, field, message, fix)

    def __str__(self) -> str:
        where = "?" if self.offset is None else str(self.offset)
        return f"{self.path}: byte {where}, {self.field}: {self.message}; {self.fix}"

    def __reduce__(self):
        return (type(self), (self.path, self.offset, self.field, self.message, self.fix))
