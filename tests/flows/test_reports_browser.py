"""The three run reports rendered in a real browser (headless Chromium): what a person sees.

Each report (``btf simulate``/``btf demo``'s ``report.html``, ``btf build-db``'s ``model/report.html``,
``btf evaluate acquisition``'s ``acquisition/report.html``) is copied to a temporary folder, a script is
injected that runs the checks on ``load`` and writes its findings as JSON into ``<pre id=result>``, and
Chromium's ``--dump-dom`` gives the page back after it ran. Checked: every image loads and is shown at
least 256 px wide, every relative link resolves to a file, no table cell holds raw JSON, every numeric
column names its unit (or is a count) and flagged cells are red (docs/evaluation.md, "Reading the
reports"). Skipped where no Chromium is on PATH (``.ci/run`` installs Debian's).
"""

from __future__ import annotations

import html
import json
import re
import shutil
import subprocess
from pathlib import Path
from urllib.parse import unquote, urlparse

import pytest

from tasks.html_report import FLAG_COLOUR, MIN_IMAGE_PX, Cell, Row, write_html

CHROMIUM = next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH (.ci/run installs Debian's)")

#: Runs in the page on load; its findings go to <pre id=result> as JSON.
CHECKS = r"""
<script>
window.addEventListener('load', () => {
  const out = {images: [], small_images: [], broken_images: [], links: [], json_cells: [], no_unit: [],
               flagged: 0, not_red: [], tables: document.querySelectorAll('table').length};
  for (const img of document.images) {
    out.images.push(img.src);
    if (!img.complete || img.naturalWidth === 0) out.broken_images.push(img.getAttribute('src'));
    const w = img.getBoundingClientRect().width;
    if (w < MIN_PX) out.small_images.push([img.getAttribute('src'), w]);
  }
  for (const a of document.querySelectorAll('a[href]')) {
    const href = a.getAttribute('href');
    if (!/^[a-z]+:/i.test(href) && !href.startsWith('#')) out.links.push([href, a.href]);
  }
  for (const td of document.querySelectorAll('td')) {
    const text = td.textContent.trim();
    if (text.startsWith('{') || text.startsWith('[')) {
      try { JSON.parse(text); out.json_cells.push(text.slice(0, 80)); } catch (e) {}
    }
  }
  const number = (text) => {
    const t = text.replace(/\[\d+\]$/, '').replace(/,/g, '').replace(/%$/, '').trim();
    if (t === '' || isNaN(Number(t))) return null;
    return /^[-+]?\d+$/.test(t) ? 'int' : 'float';
  };
  for (const table of document.querySelectorAll('table')) {
    if (!table.tHead || !table.tBodies.length) continue;
    const header = [...table.tHead.rows[0].cells].map(th => th.textContent.trim());
    header.forEach((name, j) => {
      const kinds = [...table.tBodies[0].rows].map(r => r.cells[j] ? number(r.cells[j].textContent.trim()) : null);
      if (kinds.includes('float') && !/\[[^\]]+\]\s*$/.test(name)) out.no_unit.push(name);
    });
  }
  for (const el of document.querySelectorAll('td.flag, tr.flag > td, .flag')) {
    out.flagged += 1;
    const [r, g, b] = getComputedStyle(el).color.match(/\d+/g).map(Number);
    if (!(r >= 150 && g <= 80 && b <= 80)) out.not_red.push([el.textContent.trim().slice(0, 60), `${r},${g},${b}`]);
  }
  const pre = document.createElement('pre');
  pre.id = 'result';
  pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
});
</script>
""".replace("MIN_PX", str(MIN_IMAGE_PX))


def browse(page: Path) -> dict:
    """The checks' findings on ``page`` (a copy, changed in place) after headless Chromium rendered it."""
    page.write_text(page.read_text(encoding="utf-8").replace("</body>", CHECKS + "</body>"), encoding="utf-8")
    run = subprocess.run([CHROMIUM, "--headless", "--disable-gpu", "--no-sandbox", "--allow-file-access-from-files",
                          "--window-size=1280,1000", "--virtual-time-budget=10000", "--dump-dom",
                          page.resolve().as_uri()], capture_output=True, text=True, timeout=120)
    found = re.search(r'<pre id="result">(.*?)</pre>', run.stdout, re.S)
    assert found, f"the checks did not run in {page}: {run.stderr[-2000:]}"
    return json.loads(html.unescape(found.group(1)))


def assert_readable(page: Path) -> dict:
    """Every rule of a readable report holds on ``page``; the findings."""
    found = browse(page)
    assert found["images"] and found["tables"], found
    assert not found["broken_images"], found["broken_images"]
    assert not found["small_images"], found["small_images"]
    assert not found["json_cells"], found["json_cells"]
    assert not found["no_unit"], found["no_unit"]
    assert not found["not_red"], found["not_red"]
    for href, url in found["links"]:
        assert Path(unquote(urlparse(url).path)).is_file(), f"{page.name}: link {href} resolves to nothing"
    return found


def _copy(src: Path, dst: Path) -> Path:
    """A report folder without its stores (the pages read none)."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.zarr", "scores"), dirs_exist_ok=True)
    return dst


def test_the_writer_draws_flags_red_and_images_large(tmp_path):
    from tasks.report import save_png
    import numpy as np

    (tmp_path / "f").mkdir()
    save_png(tmp_path / "f" / "tiny.png", np.full((8, 12, 3), 200, np.uint8))
    write_html(tmp_path / "r.html", "t", {"flagged": Cell(3, unit="s", flag="why"), "nested": {"a": [1, 2]}}, [
        {"title": "s", "table": [["name", "error [%]"], ["a", Cell(2.5, flag="diverged")], Row(["b", 1.5], "bad")],
         "figures": [{"file": "f/tiny.png", "caption": "tiny", "flag": "diverged"}]}],
        links=[("f/tiny.png", "the image")])
    found = assert_readable(tmp_path / "r.html")
    assert found["flagged"] >= 4 and len(found["links"]) == 2
    assert FLAG_COLOUR == "#c00000"


def test_simulate_report_reads_in_a_browser(tiny_database, tmp_path):
    assert_readable(_copy(tiny_database[1], tmp_path / "simulate") / "report.html")


def test_model_and_acquisition_reports_read_in_a_browser_and_link_back(acquisition_evaluation, model_report,
                                                                       tiny_database, tmp_path):
    from tasks.evaluate_acquisition import write_acquisition_report

    root = tmp_path / "demo"
    _copy(tiny_database[1], root)                                   # the top report, as a demo lays it out
    _copy(model_report, root / "model")
    _copy(acquisition_evaluation[0], root / "acquisition")
    assert_readable(root / "model" / "report.html")
    # written again now that the other reports are beside it: it links back to both
    summary = json.loads((root / "acquisition" / "report.json").read_text())
    write_acquisition_report(root / "acquisition", summary)
    found = assert_readable(root / "acquisition" / "report.html")
    assert {href for href, _ in found["links"]} >= {"../report.html", "../model/report.html"}
    assert len(found["images"]) >= 2 * len(summary["strategies"])
