"""tasks.html_report.write_html: the page a person reads (no browser; tests/flows/test_reports_browser.py renders
the real reports in one)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from tasks.html_report import (Cell, Row, Table, columns_without_unit, format_number, header_unit, label_of_key,
                               write_html)
from tasks.report import RELATED_REPORTS, save_png


def test_links_to_the_other_reports_are_anchors(tmp_path):
    page = write_html(tmp_path / "report.html", "t", {"a": 1}, [], links=RELATED_REPORTS).read_text()
    for href, label in RELATED_REPORTS:
        assert f"<a href='{href}'>{label}</a>" in page
    assert "See also" not in write_html(tmp_path / "bare.html", "t", {}, []).read_text()


@pytest.mark.parametrize("value,text", [(26136, "26,136"), (np.int64(7), "7"), (2.0812345, "2.081"),
                                        (234981827633.2, "234,981,827,633"), (0.25, "0.25"), (1.5e-5, "1.5e-05"),
                                        (12.5, "12.5"), (float("nan"), "NaN"), (float("inf"), "∞"), (0.0, "0"),
                                        (np.float32(0.5), "0.5"), (True, "yes")])
def test_numbers_are_formatted_for_people(value, text):
    assert format_number(value) == text


def test_no_raw_json_anywhere(tmp_path):
    summary = {"scale": {"device": "tiny", "texture": [12, 12], "per_class": {"stone": 2, "metal": 2}},
               "classes": ["stone", "metal"], "time_s": 1.25, "list of dicts": [{"a": 1, "b": 2.5}, {"a": 2}]}
    table = [["claim", "numbers"], ["a", {"abrdf": {"optimized": 1.5, "pmap7": 2.5}}], ["b", [1, 2, 3]]]
    page = write_html(tmp_path / "r.html", "t", summary, [{"title": "s", "table": table}]).read_text()
    for cell in re.findall(r"<td[^>]*>([^<]*)", page):
        text = cell.strip()
        if text[:1] in "{[":
            with pytest.raises(ValueError):
                json.loads(text)
    assert "{" not in re.sub(r"<style>.*?</style>", "", page, flags=re.S)
    assert "stone, metal" in page and "12, 12" in page and "<table class='nested'>" in page


def test_units_and_counts():
    assert header_unit("mPSNR [dB]") == "dB" and header_unit("material") is None
    assert label_of_key("exposure_time_s") == "exposure time [s]" and label_of_key("class") == "class"
    ok = [["material", "mPSNR [dB]", "texels", "mRE [%]"], ["a", 20.5, 144, "1.25"],
          ["b", Cell(2.08, flag="x"), 144, "3"]]
    assert columns_without_unit(ok) == []
    bad = Table([["material", "error", "n"], Row(["a", 0.5, 3], flag="why")])
    assert columns_without_unit(bad) == ["error"]
    assert columns_without_unit([["material", "error"], ["a", "0.25"]]) == ["error"]


def test_flags_are_red_with_their_reason(tmp_path):
    table = [["strategy", "mPSNR [dB]"], ["good", 30.0],
             ["bad", Cell(2.08, flag="diverged: condition number 3.1e+09")],
             Row(["worse", 1.0], flag="samples below the basis rank (12 < 32)")]
    page = write_html(tmp_path / "r.html", "t", {"x": Cell(3, unit="s", flag="slow")},
                      [{"title": "s", "text": ["one", "two"], "tables": [table, Table(table, caption="again")]}]
                      ).read_text()
    assert "<td class='num flag' title='diverged: condition number 3.1e+09'>2.08<sup>[1]</sup></td>" in page
    assert "<tr class='flag' title='samples below the basis rank (12 &lt; 32)'>" in page
    assert "<li>diverged: condition number 3.1e+09</li>" in page and "<li>samples below the basis rank" in page
    assert "3 s (flagged: slow)" in page and "<p>one</p>" in page and "<p>two</p>" in page
    assert "<caption>again</caption>" in page and page.count("<ol class='flags'>") == 2


def test_images_are_large_links_with_captions(tmp_path):
    (tmp_path / "f").mkdir()
    save_png(tmp_path / "f" / "small.png", np.zeros((32, 70, 3), np.uint8))
    save_png(tmp_path / "f" / "large.png", np.zeros((100, 600, 3), np.uint8))
    page = write_html(tmp_path / "r.html", "t", {}, [{"title": "s", "figures": [
        {"file": "f/small.png", "caption": "small"}, {"file": "f/large.png", "caption": "large", "flag": "diverged"}]}]
    ).read_text()
    # 70 px shown at 4 x 70 = 280 px, pixelated; 600 px at its own size; both links to the file
    assert ("<figure style='width:280px'><a href='f/small.png'><img src='f/small.png' alt='small' width='280' "
            "height='128' class='small'></a>") in page
    assert "<a href='f/large.png'><img src='f/large.png' alt='large' width='600' height='100'></a>" in page
    assert "<figcaption>small</figcaption>" in page and "flagged: diverged" in page
