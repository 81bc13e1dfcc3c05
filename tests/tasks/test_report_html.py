"""tasks.report.write_html: the page a person reads."""

from __future__ import annotations

from tasks.report import RELATED_REPORTS, write_html


def test_links_to_the_other_reports_are_anchors(tmp_path):
    page = write_html(tmp_path / "report.html", "t", {"a": 1}, [], links=RELATED_REPORTS).read_text()
    for href, label in RELATED_REPORTS:
        assert f"<a href='{href}'>{label}</a>" in page
    assert "See also" not in write_html(tmp_path / "bare.html", "t", {}, []).read_text()
