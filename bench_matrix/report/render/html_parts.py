"""Building blocks of the single-file HTML report: escaping, sortable tables, inline images, the style sheet
and the sorting script (nothing here refers to anything outside the file)."""

from __future__ import annotations

import base64
import html
import re
from collections.abc import Sequence

from bench_matrix.report.render.plots import Plot

_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")


class Html(str):
    """Text that is already HTML (built from escaped parts): `table` puts it in a cell as it is."""


def esc(text: object) -> str:
    """The text with &, <, >, " and ' escaped: safe as element content and inside attribute values."""
    return html.escape(str(text), quote=True)


def sort_value(text: str) -> str | None:
    """The number a rendered figure starts with ("2.00×", "1.00 ~", "+1.00e-04"), for sorting; None for a dash
    or any text that is not a figure."""
    found = _NUMBER.match(text.strip())
    return repr(float(found.group())) if found else None


def table(headers: Sequence[tuple[str, str]], numeric: Sequence[bool], rows: Sequence[Sequence[str]],
          row_classes: Sequence[str] = ()) -> str:
    """A sortable table: `headers` are (label, note shown on hover); numeric columns carry each cell's number
    in data-value; plain-text cells are escaped, `Html` cells are kept."""
    head = "".join(f'<th scope="col"{" class=num" if n else ""} title="{esc(note)}">{esc(label)}</th>'
                   for (label, note), n in zip(headers, numeric))
    body = []
    for k, row in enumerate(rows):
        shown = row_classes[k] if k < len(row_classes) and row_classes[k] else ""
        cells = "".join(_cell(text, n) for text, n in zip(row, numeric))
        body.append(f'<tr{f" class={shown}" if shown else ""}>{cells}</tr>')
    return (f'<div class="scroll"><table class="sortable"><thead><tr>{head}</tr></thead>'
            f'<tbody>{"".join(body)}</tbody></table></div>')


def _cell(text: str, numeric: bool) -> str:
    content = text if isinstance(text, Html) else esc(text)
    value = sort_value(text) if numeric and not isinstance(text, Html) else None
    return f'<td class=num data-value="{value}">{content}</td>' if value else \
        f"<td{' class=num' if numeric else ''}>{content}</td>"


def plot_html(plot: Plot) -> str:
    """The plot's PNG inline as a data: URI, with its title as caption."""
    data = base64.b64encode(plot.path.read_bytes()).decode("ascii")
    return (f'<figure><img src="data:image/png;base64,{data}" alt="{esc(plot.alt)}">'
            f"<figcaption>{esc(plot.title)}</figcaption></figure>")


STYLE = """
body { font: 15px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; color: #1d2330;
       margin: 0 auto; max-width: 1400px; padding: 1rem 1.5rem 3rem; }
h1 { margin-bottom: .2rem; }
h2 { border-bottom: 2px solid #d7dce5; padding-bottom: .2rem; margin-top: 2.5rem; }
h3 { margin-top: 1.6rem; }
nav a, h2 a { color: #2451a6; }
.meta { color: #5a6375; }
.scroll { overflow-x: auto; margin: .6rem 0; }
table { border-collapse: collapse; font-size: 13.5px; }
th, td { border: 1px solid #d7dce5; padding: .25rem .5rem; text-align: left; vertical-align: top; }
th { background: #eef1f6; white-space: nowrap; }
table.sortable th { cursor: pointer; user-select: none; }
table.sortable th:hover { background: #dfe5ef; }
th[aria-sort=ascending]::after { content: " \\25B2"; }
th[aria-sort=descending]::after { content: " \\25BC"; }
td.num, th.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
table.sortable td:first-child { white-space: nowrap; }
tr.baseline td { font-weight: 600; background: #f6f8fb; }
.note { border-left: 4px solid #c9a227; background: #fdf8e6; padding: .4rem .7rem; margin: .5rem 0; }
.note.bad { border-color: #c0392b; background: #fdecea; }
.group { border: 1px solid #d7dce5; border-radius: 4px; padding: .3rem .8rem; margin: .6rem 0; }
pre { white-space: pre-wrap; word-break: break-word; background: #f4f5f7; padding: .4rem .6rem;
      margin: .3rem 0; font-size: 12.5px; }
.reason { margin: .3rem 0; }
ul.cells { margin: .2rem 0 .4rem; columns: 2 22rem; }
figure { margin: 1rem 0; } figure img { max-width: 100%; height: auto; border: 1px solid #e3e6ec; }
figcaption { color: #5a6375; font-size: 13px; }
dl.columns dt { font-weight: 600; } dl.columns dd { margin: 0 0 .3rem 1rem; }
details > summary { cursor: pointer; }
"""

SCRIPT = """
(function () {
  function key(cell, numeric) {
    if (numeric) {
      var value = cell.getAttribute("data-value");
      return value === null ? null : parseFloat(value);
    }
    var text = cell.textContent.trim();
    return text === "" || text === "\\u2014" ? null : text;
  }
  function sortBy(th) {
    var table = th.closest("table"), body = table.tBodies[0];
    var index = Array.prototype.indexOf.call(th.parentNode.children, th);
    var ascending = th.getAttribute("aria-sort") !== "ascending";
    var numeric = th.classList.contains("num");
    table.querySelectorAll("th").forEach(function (h) { h.removeAttribute("aria-sort"); });
    th.setAttribute("aria-sort", ascending ? "ascending" : "descending");
    var rows = Array.prototype.slice.call(body.rows);
    rows.sort(function (a, b) {
      var x = key(a.cells[index], numeric), y = key(b.cells[index], numeric);
      if (x === null || y === null) { return x === y ? 0 : (x === null ? 1 : -1); }
      var order = numeric ? x - y : x.localeCompare(y);
      return ascending ? order : -order;
    });
    rows.forEach(function (row) { body.appendChild(row); });
  }
  document.querySelectorAll("table.sortable th").forEach(function (th) {
    th.tabIndex = 0;
    th.addEventListener("click", function () { sortBy(th); });
    th.addEventListener("keydown", function (event) {
      if (event.key === "Enter" || event.key === " ") { event.preventDefault(); sortBy(th); }
    });
  });
})();
"""
