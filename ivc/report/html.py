"""The report as one self-contained HTML page: inline CSS, figures embedded as base64 PNG."""

from __future__ import annotations

import base64
from html import escape

_STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1180px; margin: 2em auto; padding: 0 1em; color: #222; }
h1 { margin-bottom: 0.2em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: 0.2em; margin-top: 2em; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th:first-child, td:first-child { text-align: left; } th { background: #f3f3f3; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.92em; color: #444; margin-top: 0.3em; }
.meta { color: #555; font-size: 0.92em; } .warn { background: #fff4d6; border-left: 4px solid #e0a800;
padding: 0.5em 0.8em; } .missing { color: #a33; }
"""

_PERCENTILES = (("p25", "25%"), ("p50", "50%"), ("p75", "75%"), ("p95", "95%"), ("p99", "99%"), ("max", "max"))


def table(header: list[str] | None, rows: list[list]) -> str:
    """An HTML table (no header row when ``header`` is None); floats get 4 significant digits."""
    def cell(value) -> str:
        return f"{value:.4g}" if isinstance(value, float) else escape(str(value))

    head = "" if header is None else "<tr>" + "".join(f"<th>{escape(h)}</th>" for h in header) + "</tr>"
    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in row) + "</tr>" for row in rows)
    return f"<table>{head}{body}</table>"


def percentile_table(rows: list[tuple[str, dict, str]]) -> str:
    """Rows of (label, percentiles dict, unit) in the layout of Himberg 2010's Table 24."""
    body = [[label, *[values.get(k, "") for k, _ in _PERCENTILES], unit] for label, values, unit in rows]
    return table(["", *[h for _, h in _PERCENTILES], "unit"], body)


def figure(name: str, png: bytes, title: str, caption: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return (f'<figure id="fig-{escape(name)}"><img alt="{escape(title)}" src="data:image/png;base64,{data}">'
            f"<figcaption><b>{escape(title)}.</b> {escape(caption)}</figcaption></figure>")


def missing(reason: str) -> str:
    return f'<p class="missing">Not drawn: {escape(reason)}</p>'


def page(title: str, meta: list[str], warnings: list[str], sections: list[tuple[str, str, str]]) -> str:
    """``sections``: (anchor, heading, inner HTML)."""
    contents = "".join(f'<li><a href="#{a}">{escape(h)}</a></li>' for a, h, _ in sections)
    body = "".join(f'<section id="{a}"><h2>{escape(h)}</h2>{inner}</section>' for a, h, inner in sections)
    notes = "".join(f'<p class="warn">{escape(w)}</p>' for w in warnings)
    lines = "<br>".join(escape(m) for m in meta)
    return (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{escape(title)}</title>'
            f"<style>{_STYLE}</style></head><body><h1>{escape(title)}</h1><p class=\"meta\">{lines}</p>{notes}"
            f"<ul>{contents}</ul>{body}</body></html>\n")
