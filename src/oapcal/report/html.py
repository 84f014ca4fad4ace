"""One self-contained HTML page: inline CSS (screen and print), images as base64 PNG, no
scripts and no external resources, so it opens anywhere and prints as it looks.

>>> page = document("T", [section("A", table(["x"], [[1.5]]))])
>>> page.startswith("<!DOCTYPE html>") and "<td>1.5</td>" in page
True
"""

from __future__ import annotations

import base64
import html
import math

CSS = """
:root { --ink: #1d2330; --muted: #5b6475; --rule: #d5d9e0; --accent: #2b5c9e; --bad: #a8322d; }
* { box-sizing: border-box; }
body { font: 15px/1.5 system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif;
       color: var(--ink); max-width: 1180px; margin: 0 auto; padding: 24px 28px 48px; background: #fff; }
h1 { font-size: 1.7em; margin: 0 0 4px; }
h2 { font-size: 1.25em; margin: 32px 0 8px; padding-bottom: 4px; border-bottom: 2px solid var(--rule);
     color: var(--accent); }
p.meta, p.note, figcaption { color: var(--muted); font-size: 0.9em; }
nav { margin: 12px 0 8px; font-size: 0.9em; }
nav a { color: var(--accent); margin-right: 14px; text-decoration: none; }
table { border-collapse: collapse; margin: 8px 0 12px; font-size: 0.92em; }
caption { text-align: left; font-weight: 600; padding: 4px 0; }
th, td { border: 1px solid var(--rule); padding: 3px 9px; text-align: right; }
th { background: #f1f3f7; }
td:first-child, th:first-child { text-align: left; }
tr.dim td { color: #9aa1ad; }
tr.best td { background: #eef6ee; }
td.bad { color: var(--bad); font-weight: 600; }
figure { margin: 10px 0 18px; }
figure img { max-width: 100%; height: auto; border: 1px solid var(--rule); }
.grid { display: flex; flex-wrap: wrap; gap: 18px; align-items: flex-start; }
.grid > * { flex: 1 1 420px; }
@media print {
  @page { size: A4; margin: 12mm; }
  body { max-width: none; padding: 0; font-size: 10.5pt; }
  nav { display: none; }
  h2 { break-after: avoid; page-break-after: avoid; }
  figure, table { break-inside: avoid; page-break-inside: avoid; }
  figure img { border: none; }
  a { color: inherit; text-decoration: none; }
}
"""


def esc(value) -> str:
    return html.escape(str(value), quote=True)


def fmt(value, digits: int = 4) -> str:
    """A number for a table: ``digits`` significant digits, ``-`` for None/NaN."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return "-"
        return f"{value:.{digits}g}"
    return str(value)


def table(headers, rows, caption: str | None = None, row_classes=None, cell_classes=None) -> str:
    """An HTML table; cells are formatted with :func:`fmt` and escaped."""
    out = ["<table>"]
    if caption:
        out.append(f"<caption>{esc(caption)}</caption>")
    out.append("<thead><tr>" + "".join(f"<th>{esc(h)}</th>" for h in headers) + "</tr></thead><tbody>")
    for i, row in enumerate(rows):
        cls = row_classes[i] if row_classes else ""
        cells = []
        for j, v in enumerate(row):
            cc = cell_classes[i][j] if cell_classes else ""
            cells.append(f"<td{f' class={chr(34)}{cc}{chr(34)}' if cc else ''}>{esc(fmt(v))}</td>")
        out.append(f"<tr{f' class={chr(34)}{cls}{chr(34)}' if cls else ''}>" + "".join(cells) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def png_figure(png: bytes, alt: str, caption: str | None = None) -> str:
    """A figure with the PNG embedded as a data URI."""
    data = base64.b64encode(png).decode("ascii")
    cap = f"<figcaption>{esc(caption)}</figcaption>" if caption else ""
    return f'<figure><img src="data:image/png;base64,{data}" alt="{esc(alt)}">{cap}</figure>'


def paragraph(text: str, cls: str = "note") -> str:
    return f'<p class="{cls}">{esc(text)}</p>'


def section(title: str, body: str, anchor: str | None = None) -> tuple[str, str, str]:
    """A section ``(anchor, title, body html)``."""
    anchor = anchor or "".join(c if c.isalnum() else "-" for c in title.lower()).strip("-")
    return anchor, title, body


def document(title: str, sections, meta: str = "") -> str:
    """The whole page."""
    nav = "".join(f'<a href="#{esc(a)}">{esc(t)}</a>' for a, t, _ in sections)
    body = "".join(f'<section id="{esc(a)}"><h2>{esc(t)}</h2>{b}</section>' for a, t, b in sections)
    return (
        "<!DOCTYPE html>\n"
        '<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{esc(title)}</title><style>{CSS}</style></head><body>"
        f"<h1>{esc(title)}</h1>"
        + (f'<p class="meta">{esc(meta)}</p>' if meta else "")
        + f"<nav>{nav}</nav>{body}</body></html>\n"
    )
