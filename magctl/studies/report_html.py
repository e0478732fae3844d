"""``report.html``: the report of ``magctl reproduce`` as one self-contained page, written beside ``report.md``.

The page carries what ``report.md`` carries — the claims table, the paper-vs-magctl quantities, then one section
per study with its summary and figures — and reads nothing else once written: the Markdown is converted with the
``markdown`` package (tables extension), every figure (PNG, and the GIF animations, which play inline) is a
base64 ``data:`` URI, and there is no network URL. Where plotly is importable (the ``view`` extra) the sections
of the push studies also get interactive charts of numbers their ``results`` already hold (share converged and
error by attempt, attempts per trial, the side-push curve), with plotly.js inlined once; without plotly the page
says how to get them and shows the static figures only.
"""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path
from typing import Any

from magctl.studies.report import claims_table, quantities_table
from magctl.studies.runner import StudyResult

INSTALL_HINT = "Interactive plots need plotly: <code>pip install -e '.[view]'</code> in a checkout."
"""The line a page written without plotly carries instead of its interactive charts."""

MIME = {".png": "image/png", ".gif": "image/gif", ".jpg": "image/jpeg", ".jpeg": "image/jpeg",
        ".svg": "image/svg+xml", ".webp": "image/webp"}

STYLE = """
body { font: 15px/1.5 system-ui, sans-serif; max-width: 75rem; margin: 2rem auto; padding: 0 1rem; color: #222; }
h1, h2 { border-bottom: 1px solid #ddd; padding-bottom: .2rem; }
nav ul { columns: 2; }
table { border-collapse: collapse; display: block; overflow-x: auto; margin: 1rem 0; font-size: 13px; }
th, td { border: 1px solid #ccc; padding: .25rem .5rem; vertical-align: top; }
th { background: #f3f3f3; }
tr:nth-child(even) td { background: #fafafa; }
figure { margin: 1rem 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption, .wall, .note { color: #666; font-size: 13px; }
code { background: #f3f3f3; padding: 0 .2rem; }
"""


def _slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-") or "study"


def markdown_html(lines: list[str]) -> str:
    """Markdown ``lines`` as HTML (tables extension); a table run gets the blank lines around it that
    Python-Markdown needs and a Markdown viewer does not."""
    import markdown

    out: list[str] = []
    for line in (part for text in lines for part in str(text).split("\n")):
        row, prev = line.lstrip().startswith("|"), out[-1] if out else ""
        if prev.strip() and row != prev.lstrip().startswith("|"):
            out.append("")
        out.append(line)
    return markdown.markdown("\n".join(out), extensions=["tables"])


def data_uri(path: Path) -> str:
    """The file at ``path`` as a base64 ``data:`` URI (its type from its suffix)."""
    mime = MIME.get(path.suffix.lower(), "application/octet-stream")
    return f"data:{mime};base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def _figure(fig: Path) -> str:
    path = Path(fig)
    if not path.is_file():
        return f'<p class="note">figure {html.escape(path.name)} was not found when the report was written</p>'
    name = html.escape(path.stem)
    return f'<figure><img src="{data_uri(path)}" alt="{name}"><figcaption>{name}</figcaption></figure>'


# --- interactive charts: built from the numbers a study returned, never from anything else -----------------

def _numbers(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(v is None or isinstance(v, int | float) for v in value)


def _summaries(results: dict) -> dict[str, dict]:
    """The per-controller summaries (``magctl.studies.push.controller_summary``) a push study returns."""
    for key in ("controllers", "methods"):
        group = results.get(key)
        if isinstance(group, dict):
            found = {str(label): s for label, s in group.items() if isinstance(s, dict)}
            if found:
                return found
    return {}


def charts(result: StudyResult) -> list[tuple[str, Any]]:
    """``(div id, plotly figure)`` for each interactive chart of ``result``; plotly must be importable."""
    import plotly.graph_objects as go

    slug, out = _slug(result.name), []
    summaries = _summaries(result.results)

    def attempts(n: int) -> dict:     # whole attempts on the axis
        return dict(tick0=0, dtick=1 if n <= 20 else 5)

    def layout(title: str, x: str, y: str, **kw) -> dict:
        return dict(title=dict(text=title, font=dict(size=14)), xaxis_title=x, yaxis_title=y, template="plotly_white",
                    margin=dict(l=60, r=20, t=50, b=50), legend=dict(font=dict(size=11)), **kw)

    conv = {k: s["converged_by_attempt"] for k, s in summaries.items() if _numbers(s.get("converged_by_attempt"))}
    if conv:
        fig = go.Figure([go.Scatter(x=list(range(1, len(v) + 1)), y=[100 * f for f in v], mode="lines+markers",
                                    line_shape="hv", name=k) for k, v in conv.items()])
        fig.update_layout(**layout("Trials converged by attempt", "attempt", "converged (%)",
                                   yaxis_range=[0, 102], xaxis=attempts(max(map(len, conv.values())))))
        out.append((f"plot-{slug}-converged", fig))
    err = {k: s for k, s in summaries.items() if _numbers(s.get("mean_error_um_by_attempt"))}
    if err:
        traces = []
        for k, s in err.items():
            mean, std = s["mean_error_um_by_attempt"], s.get("std_error_um_by_attempt")
            bars = dict(type="data", array=std, visible=True, thickness=1) if _numbers(std) else None
            traces.append(go.Scatter(x=list(range(len(mean))), y=mean, error_y=bars, mode="lines+markers", name=k))
        fig = go.Figure(traces)
        fig.update_layout(**layout("Error after each attempt, mean ± std over trials (a finished trial's last "
                                   "error carried)", "attempt (0: before the first)", "error (µm)",
                                   xaxis=attempts(max(len(s["mean_error_um_by_attempt"]) for s in err.values()))))
        out.append((f"plot-{slug}-errors", fig))
    att = {k: s["attempts_all"] for k, s in summaries.items() if _numbers(s.get("attempts_all"))}
    if att:
        fig = go.Figure([go.Box(x=v, name=k, boxpoints="all", jitter=0.4, pointpos=0, orientation="h")
                         for k, v in att.items()])
        fig.update_layout(**layout("Attempts per trial (a trial that did not converge counted at the budget)",
                                   "attempts", "", showlegend=False, height=max(320, 60 + 50 * len(att)),
                                   yaxis_autorange="reversed",
                                   xaxis=attempts(max((a for v in att.values() for a in v if a is not None),
                                                      default=1))))
        out.append((f"plot-{slug}-attempts", fig))
    points = result.results.get("points")
    if isinstance(points, list) and points and all(isinstance(p, dict) and "gap_um" in p and "displacement_um" in p
                                                   for p in points):
        traces = []
        for contact, label in ((False, "no contact"), (True, "contact")):
            sel = [p for p in points if bool(p.get("contact")) == contact]
            if sel:
                traces.append(go.Scatter(x=[p["gap_um"] for p in sel], y=[p["displacement_um"] for p in sel],
                                         mode="markers+lines" if not contact else "markers", name=label))
        paper = result.results.get("against_eq22")
        if isinstance(paper, dict) and _numbers(paper.get("gaps_um")) and _numbers(paper.get("eq22_um")):
            traces.append(go.Scatter(x=paper["gaps_um"], y=paper["eq22_um"], mode="markers", name="paper eq 22",
                                     marker=dict(symbol="x", size=10)))
        positive = all(isinstance(p["displacement_um"], int | float) and p["displacement_um"] > 0 for p in points)
        fig = go.Figure(traces)
        fig.update_layout(**layout("Side-push displacement D_s versus side gap D_g", "gap D_g (µm)",
                                   "displacement D_s (µm)", yaxis_type="log" if positive else "linear"))
        out.append((f"plot-{slug}-curve", fig))
    return out


def _plotly():
    """``(plotly.io, the plotly.js source)``, or None without plotly."""
    try:
        import plotly.io as pio
        from plotly.offline import get_plotlyjs
    except ImportError:
        return None
    return pio, get_plotlyjs()


def render(results: list[StudyResult], timings: dict[str, float], conditions: str = "magctl") -> str:
    """The page's HTML text."""
    from magctl.studies.conditions import CONDITIONS

    plotly = _plotly()
    sections: list[tuple[str, str, list[str]]] = []    # (id, heading, body parts)
    table, rows = claims_table(results, conditions), quantities_table(results)
    if table:
        sections.append(("claims", "The paper's claims, one row each", [markdown_html(table)]))
    if rows:
        sections.append(("quantities", "Paper vs magctl: quantities", [markdown_html(rows)]))
    any_chart = False
    for r in results:
        body = [f'<p class="wall">wall time {timings.get(r.name, 0.0):.1f} s</p>', markdown_html(r.summary)]
        body += [_figure(fig) for fig in r.figures]
        if plotly is not None:
            pio, _ = plotly
            for div_id, fig in charts(r):
                any_chart = True
                body.append(pio.to_html(fig, include_plotlyjs=False, full_html=False, div_id=div_id,
                                        default_width="100%", default_height=f"{fig.layout.height or 420}px",
                                        config={"displaylogo": False, "responsive": True}))
        sections.append((f"study-{_slug(r.name)}", r.name, body))

    head = ["<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
            '<meta name="viewport" content="width=device-width, initial-scale=1">',
            "<title>magctl reproduce — report</title>", f"<style>{STYLE}</style>"]
    if plotly is not None and any_chart:
        head.append(f'<script type="text/javascript">{plotly[1]}</script>')
    page = [*head, "</head>", "<body>", "<h1>magctl reproduce — report</h1>",
            f"<p>Conditions: <strong>{html.escape(conditions)}</strong> — {html.escape(CONDITIONS[conditions])}.</p>"]
    if plotly is None:
        page.append(f'<p class="note">{INSTALL_HINT}</p>')
    page += ["<nav><h2>Contents</h2><ul>",
             *(f'<li><a href="#{sid}">{html.escape(title)}</a></li>' for sid, title, _ in sections), "</ul></nav>"]
    for sid, title, body in sections:
        page += [f'<section id="{sid}">', f"<h2>{html.escape(title)}</h2>", *body, "</section>"]
    page += ["</body>", "</html>", ""]
    return "\n".join(page)


def write_html_report(out: Path, results: list[StudyResult], timings: dict[str, float],
                      conditions: str = "magctl") -> Path:
    """Write ``out/report.html`` (see the module's docstring) and return its path."""
    path = Path(out) / "report.html"
    path.write_text(render(results, timings, conditions), encoding="utf-8")
    return path
