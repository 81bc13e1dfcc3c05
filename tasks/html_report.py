"""The one HTML writer of the run reports: pages a person can read, with units, flags and large figures.

Every ``report.html`` (``btf demo`` / ``btf simulate``, ``btf build-db``,
``btf evaluate acquisition``) is written by :func:`write_html`. The rules it
keeps (docs/evaluation.md, "Reading the reports"; tested in a real browser by
``tests/flows/test_reports_browser.py``):

* **No raw JSON.** A dict is shown as a small nested table, a list of scalars
  as a comma-separated list, a list of dicts as a table; numbers are formatted
  by :func:`format_number` (significant digits, thousands separators).
* **Units.** A table's header names each column's unit in square brackets,
  ``"mPSNR [dB]"``, ``"time [s]"``, ``"ratio [1]"``; a column of whole numbers
  is a count and needs none. :func:`columns_without_unit` lists the numeric
  columns of a table that lack one (for tests).
* **Flags.** A cell or a row can be flagged with a reason: it is drawn in red,
  the reason is its ``title`` and a numbered footnote under the table.
* **Figures** are links to their image file (click to enlarge) with a caption;
  an image narrower than :data:`MIN_IMAGE_PX` is enlarged by a whole factor
  with ``image-rendering: pixelated``. A figure can be flagged like a cell.

API
---
``write_html(path, title, summary, sections, links=())``

``summary``
    ``{label: value}``, shown as a key/value table under the title.
``sections``
    A list of dicts, each with:

    * ``"title"``: str (required);
    * ``"text"``: str or list of str, one paragraph each;
    * ``"table"``: one table, and/or ``"tables"``: several. A table is a list
      of rows, the header row first, or a :class:`Table` (``rows``, ``caption``);
    * ``"figures"``: list of ``{"file": path relative to the page, "caption":
      str, "flag": reason (optional)}``;
    * ``"notes"``: str or list of str, paragraphs after the tables and figures.

    A row is a list of values or a :class:`Row` (``cells``, ``flag``); a
    value is a str, a number, None (shown as a dash), a dict or list (nested),
    or a :class:`Cell` (``value``, ``unit``, ``flag``, ``digits``); a dict with the key ``"value"`` and
    no other keys than those (``{"value": 2.08, "flag": "diverged: ..."}``) is read as a :class:`Cell`, so
    that tables kept in JSON can carry flags.
``links``
    ``[(href, label)]``, a "See also" line under the title.
"""

from __future__ import annotations

import html
import math
import re
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["FLAG_COLOUR", "MIN_IMAGE_PX", "Cell", "Row", "Table", "as_cell", "columns_without_unit", "format_number",
           "header_unit", "label_of_key", "png_size", "write_html"]

#: Narrowest an image is shown, CSS pixels (smaller ones are enlarged by a whole factor).
MIN_IMAGE_PX = 256

#: Flag colour (CSS); the browser test checks flagged cells are drawn in it.
FLAG_COLOUR = "#c00000"

_CSS = (
    "body{font-family:sans-serif;max-width:1200px;margin:auto;padding:1em;line-height:1.4}"
    "figure{display:inline-block;vertical-align:top;margin:6px;text-align:center;font-size:12px;max-width:100%}"
    "figure img{border:1px solid #ccc;max-width:100%;height:auto}"
    f"img.small{{image-rendering:pixelated;min-width:{MIN_IMAGE_PX}px}}"
    "table{border-collapse:collapse;margin:0.5em 0}"
    "td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px;text-align:left;vertical-align:top}"
    "td.num{text-align:right;font-variant-numeric:tabular-nums}"
    "table.nested td,table.nested th{font-size:12px;padding:1px 5px}"
    "caption{caption-side:top;text-align:left;font-weight:bold;font-size:13px}"
    f".flag,.flag td,.flag th{{color:{FLAG_COLOUR}}} td.flag,tr.flag td{{background:#fff0f0}}"
    f"ol.flags{{color:{FLAG_COLOUR};font-size:12px;margin-top:0}}"
)


@dataclass(frozen=True)
class Cell:
    """A table cell or summary value with a unit, a flag (its reason) or its own significant digits."""

    value: Any
    unit: str | None = None
    flag: str | None = None
    digits: int = 4


@dataclass(frozen=True)
class Row:
    """A table row, flagged as a whole when ``flag`` (the reason) is given."""

    cells: Sequence[Any]
    flag: str | None = None


@dataclass(frozen=True)
class Table:
    """A table: ``rows`` with the header row first, an optional caption above it."""

    rows: Sequence[Any]
    caption: str = ""
    notes: Sequence[str] = field(default_factory=tuple)


_CELL_KEYS = {"value", "unit", "flag", "digits"}


def as_cell(value: Any) -> Any:
    """``value``, or the :class:`Cell` a JSON cell ``{"value": v, "flag": reason, ...}`` stands for."""
    if isinstance(value, Mapping) and "value" in value and set(value) <= _CELL_KEYS:
        return Cell(**value)
    return value


# --------------------------------------------------------------------------- values


def format_number(x: Any, digits: int = 4) -> str:
    """A number as a person reads it.

    Whole numbers with thousands separators (``"26,136"``); floats to
    ``digits`` significant digits, with thousands separators from 10^digits
    up (``"234,981,827,633"``), exponent notation below 10^-3
    (``"1.234e-05"``); ``"NaN"``, ``"∞"``, ``"−∞"`` for non-finite values.
    """
    if isinstance(x, bool):
        return "yes" if x else "no"
    if hasattr(x, "item") and not isinstance(x, (list, tuple, dict)):
        x = x.item()                                                   # numpy scalar
    if isinstance(x, int):
        return f"{x:,}"
    x = float(x)
    if math.isnan(x):
        return "NaN"
    if math.isinf(x):
        return "∞" if x > 0 else "−∞"
    if x == 0:
        return "0"
    if abs(x) >= 10 ** digits:
        return f"{x:,.0f}"
    if abs(x) < 1e-3:
        return f"{x:.{digits}g}"
    return f"{x:,.{digits}g}"


def _is_number(x: Any) -> bool:
    if isinstance(x, bool):
        return False
    if isinstance(x, (int, float)):
        return True
    return hasattr(x, "dtype") and getattr(x, "shape", None) == () and x.dtype.kind in "iuf"


#: Key suffixes of JSON-ish dicts and their units (``exposure_time_s`` -> ``exposure time [s]``).
_KEY_UNITS = (("_percent", "%"), ("_db", "dB"), ("_mb_per_s", "MB/s"), ("_px", "px"), ("_s", "s"), ("_h", "h"),
              ("_m", "m"))


def label_of_key(key: Any) -> str:
    """A dict key as a label: underscores as spaces, a unit suffix as ``[unit]`` (``"time_s"`` -> ``"time [s]"``)."""
    text = str(key)
    for suffix, unit in _KEY_UNITS:
        if text.endswith(suffix) and len(text) > len(suffix):
            return f"{text[:-len(suffix)].replace('_', ' ')} [{unit}]"
    return text.replace("_", " ")


def _value_html(value: Any, unit: str | None = None, digits: int = 4) -> str:
    """One value as HTML: text escaped, numbers formatted, dicts and lists nested (never JSON)."""
    value = as_cell(value)
    if isinstance(value, Cell):
        return _value_html(value.value, value.unit or unit, value.digits)
    if value is None:
        return "–"
    if isinstance(value, str):
        text = html.escape(value)
    elif _is_number(value) or isinstance(value, bool):
        text = format_number(value, digits)
    elif isinstance(value, Mapping):
        return _nested_table(value)
    elif isinstance(value, Path):
        text = html.escape(str(value))
    elif hasattr(value, "tolist") or isinstance(value, (list, tuple, set)):
        items = list(value.tolist() if hasattr(value, "tolist") else value)
        if items and all(isinstance(v, Mapping) for v in items):
            keys = list(dict.fromkeys(k for v in items for k in v))
            return _table_html([[label_of_key(k) for k in keys]] + [[v.get(k) for k in keys] for v in items],
                               nested=True)
        if any(isinstance(v, (list, tuple, Mapping)) for v in items):
            return "; ".join(_value_html(v) for v in items)
        text = ", ".join(_value_html(v, None, digits) for v in items)
    else:
        text = html.escape(str(value))
    return f"{text} {html.escape(unit)}" if unit else text


def _nested_table(mapping: Mapping) -> str:
    rows = "".join(f"<tr><th>{html.escape(label_of_key(k))}</th><td{_num_class(v)}>{_value_html(v)}</td></tr>"
                   for k, v in mapping.items())
    return f"<table class='nested'>{rows}</table>"


def _num_class(value: Any) -> str:
    value = as_cell(value)
    inner = value.value if isinstance(value, Cell) else value
    return " class='num'" if _is_number(inner) else ""


# --------------------------------------------------------------------------- tables


def header_unit(header: str) -> str | None:
    """The unit a column header names in square brackets at its end (``"mPSNR [dB]"`` -> ``"dB"``), or None."""
    match = re.search(r"\[([^\]]+)\]\s*$", str(header))
    return match.group(1) if match else None


def _numeric_kind(value: Any) -> str | None:
    """``'int'``, ``'float'`` or None (not a number) of a cell, also of a number written as text."""
    value = as_cell(value)
    value = value.value if isinstance(value, Cell) else value
    if isinstance(value, str):
        text = value.replace(",", "").strip().rstrip("%").strip()
        try:
            float(text)
        except ValueError:
            return None
        return "int" if re.fullmatch(r"[-+]?\d+", text) else "float"
    if _is_number(value):
        kind = getattr(value, "dtype", None)
        return "int" if isinstance(value, int) or (kind is not None and kind.kind in "iu") else "float"
    return None


def columns_without_unit(rows: Sequence[Any] | Table) -> list[str]:
    """Headers of the columns holding a non-whole number in some row but naming no ``[unit]`` (empty: all good).

    A column of whole numbers only is a count and needs no unit.
    """
    rows = rows.rows if isinstance(rows, Table) else rows
    header, *body = rows
    missing = []
    for j, name in enumerate(header):
        cells = [r[j] for r in (r.cells if isinstance(r, Row) else r for r in body) if j < len(r)]
        if any(_numeric_kind(c) == "float" for c in cells) and header_unit(name) is None:
            missing.append(str(name))
    return missing


class _Footnotes:
    """Flag reasons of one table, numbered in order of appearance (a reason once)."""

    def __init__(self) -> None:
        self.reasons: list[str] = []

    def mark(self, reason: str) -> str:
        if reason not in self.reasons:
            self.reasons.append(reason)
        n = self.reasons.index(reason) + 1
        return f"<sup>[{n}]</sup>"

    def html(self) -> str:
        if not self.reasons:
            return ""
        return "<ol class='flags'>" + "".join(f"<li>{html.escape(r)}</li>" for r in self.reasons) + "</ol>"


def _table_html(rows: Sequence[Any], caption: str = "", nested: bool = False, notes: Sequence[str] = ()) -> str:
    header, *body = rows
    footnotes = _Footnotes()
    out = [f"<table class='{'nested' if nested else 'data'}'>"]
    if caption:
        out.append(f"<caption>{html.escape(caption)}</caption>")
    out.append("<thead><tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in header) + "</tr></thead><tbody>")
    for row in body:
        cells, row_flag = (row.cells, row.flag) if isinstance(row, Row) else (row, None)
        tds = []
        for j, value in enumerate(cells):
            value = as_cell(value)
            flag = value.flag if isinstance(value, Cell) else None
            classes = ["num"] if _numeric_kind(value) else []
            attrs = ""
            mark = ""
            if flag:
                classes.append("flag")
                attrs = f" title='{html.escape(flag)}'"
                mark = footnotes.mark(flag)
            if row_flag and j == 0:
                mark += footnotes.mark(row_flag)
            cls = f" class='{' '.join(classes)}'" if classes else ""
            tds.append(f"<td{cls}{attrs}>{_value_html(value)}{mark}</td>")
        row_attrs = f" class='flag' title='{html.escape(row_flag)}'" if row_flag else ""
        out.append(f"<tr{row_attrs}>" + "".join(tds) + "</tr>")
    out.append("</tbody></table>")
    out.append(footnotes.html())
    out += [f"<p>{html.escape(n)}</p>" for n in notes]
    return "".join(out)


# --------------------------------------------------------------------------- figures


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of a PNG from its header, or None when ``path`` is no readable PNG."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    return struct.unpack(">II", head[16:24])


def _figure_html(fig: Mapping[str, Any], page_dir: Path) -> str:
    src = html.escape(str(fig["file"]))
    size = png_size(page_dir / fig["file"])
    attrs, figure = " class='small'", "<figure>"
    if size is not None:                         # the figure as wide as its image, so the caption wraps under it
        w, h = size
        scale = max(1, math.ceil(MIN_IMAGE_PX / max(w, 1)))
        attrs = f" width='{w * scale}' height='{h * scale}'" + (" class='small'" if scale > 1 else "")
        figure = f"<figure style='width:{w * scale}px'>"
    caption = html.escape(str(fig.get("caption", "")))
    flag = fig.get("flag")
    if flag:
        caption = (f"<span class='flag' title='{html.escape(flag)}'>{caption}<br>"
                   f"flagged: {html.escape(flag)}</span>")
    alt = html.escape(str(fig.get("caption") or Path(str(fig["file"])).name))
    return (f"{figure}<a href='{src}'><img src='{src}' alt='{alt}'{attrs}></a>"
            f"<figcaption>{caption}</figcaption></figure>")


# --------------------------------------------------------------------------- the page


def _paragraphs(text: str | Sequence[str] | None) -> str:
    if not text:
        return ""
    items = [text] if isinstance(text, str) else [p for p in text if p]
    return "".join(f"<p>{html.escape(p)}</p>" for p in items)


def _section_html(section: Mapping[str, Any], page_dir: Path) -> str:
    parts = [f"<h2>{html.escape(section['title'])}</h2>", _paragraphs(section.get("text"))]
    tables = ([section["table"]] if section.get("table") else []) + list(section.get("tables") or [])
    for table in tables:
        if isinstance(table, Table):
            parts.append(_table_html(table.rows, table.caption, notes=table.notes))
        else:
            parts.append(_table_html(table))
    parts += [_figure_html(fig, page_dir) for fig in section.get("figures") or []]
    parts.append(_paragraphs(section.get("notes")))
    return "\n".join(p for p in parts if p)


def write_html(path: str | Path, title: str, summary: Mapping[str, Any], sections: Sequence[Mapping[str, Any]],
               links: Sequence[tuple[str, str]] = ()) -> Path:
    """Write a self-contained HTML page of a summary and figure/table sections (images beside it).

    Parameters
    ----------
    path : path
        The page; figure files are relative to its folder.
    title : str
    summary : mapping
        ``{label: value}`` under the title (values as in the module docstring).
    sections : sequence of mapping
        ``{"title", "text", "table", "tables", "figures", "notes"}`` (module docstring).
    links : sequence of (href, label)
        Related pages, a "See also" line under the title.

    Returns
    -------
    path : Path
    """
    path = Path(path)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             f"<style>{_CSS}</style></head><body>", f"<h1>{html.escape(title)}</h1>"]
    if links:
        parts.append("<p>See also: " + " | ".join(f"<a href='{html.escape(href)}'>{html.escape(label)}</a>"
                                                  for href, label in links) + "</p>")
    if summary:
        parts.append("<table class='summary'>" + "".join(
            f"<tr><th>{html.escape(str(k))}</th><td{_num_class(v)}>{_summary_value(v)}</td></tr>"
            for k, v in summary.items()) + "</table>")
    parts += [_section_html(section, path.parent) for section in sections]
    parts.append("</body></html>")
    path.write_text("\n".join(parts), encoding="utf-8")
    return path


def _summary_value(value: Any) -> str:
    """A summary value; a flagged one in red with its reason written out."""
    value = as_cell(value)
    if isinstance(value, Cell) and value.flag:
        return (f"<span class='flag' title='{html.escape(value.flag)}'>{_value_html(value)} "
                f"(flagged: {html.escape(value.flag)})</span>")
    return _value_html(value)
