"""report.json, report.csv and index.html (before/after thumbnails, the whole model and the
changed part's close-up, with each scan's figures)."""

from __future__ import annotations

import csv
import html
import io
import json
import os
from pathlib import Path
from typing import Any
from urllib.parse import quote

from ..io import atomic_write

COLUMNS = ("scan", "status", "points", "constraints", "kept", "method", "centers", "residual",
           "constraint_error",
           "constraint_error_rel", "converged", "seconds", "load", "rings", "fit", "basis",
           "apply", "save", "render", "output", "png", "closeup", "error")


def printable(text: Any) -> str:
    """``text`` as valid UTF-8: a name that is not (a non-UTF-8 file or member name, decoded by
    Python with surrogate escapes) shows replacement characters instead of failing the write."""
    return str(text).encode("utf-8", "surrogateescape").decode("utf-8", "replace")


def clean(value: Any) -> Any:
    """A copy of a row / summary with every string made :func:`printable`."""
    if isinstance(value, str):
        return printable(value)
    if isinstance(value, dict):
        return {printable(k): clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean(v) for v in value]
    return value


def _flat(row: dict[str, Any]) -> dict[str, Any]:
    flat = {k: row.get(k) for k in COLUMNS}
    for stage, value in (row.get("timings") or {}).items():
        if stage in flat:
            flat[stage] = value
    return {k: ("" if v is None else v) for k, v in flat.items()}


def _write_text(path: Path, text: str) -> None:
    with atomic_write(path) as f:
        f.write(text.encode())


def _fmt(value: Any, spec: str) -> str:
    if value is None or value == "":
        return "–"
    try:
        return format(value, spec)
    except (TypeError, ValueError):
        return html.escape(str(value))


def write_reports(output_dir: Path, rows: list[dict[str, Any]], summary: dict[str, Any]) -> None:
    """report.json, report.csv and index.html, each written atomically. Every name is made valid
    UTF-8 first (so no name can stop the report), and HTML-escaped in the page."""
    output_dir.mkdir(parents=True, exist_ok=True)
    rows, summary = clean(rows), clean(summary)
    _write_text(output_dir / "report.json",
                json.dumps({**summary, "scans": rows}, indent=1, default=str))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS)
    writer.writeheader()
    for row in rows:
        writer.writerow(_flat(row))
    _write_text(output_dir / "report.csv", buf.getvalue())
    _write_text(output_dir / "index.html", _html(output_dir, rows, summary))


def _rel(path: str | None, base: Path) -> str | None:
    """A link to ``path`` that can only be a relative file link: ``./`` then the relative path
    percent-encoded (a name like ``javascript:alert(1).ply`` cannot become a scheme), escaped
    for an attribute; None when there is no such file under ``base``."""
    if not path:
        return None
    try:
        if not Path(path).is_file():
            return None
        rel = os.path.relpath(path, base)
    except (OSError, ValueError):
        return None
    if rel.startswith(".."):
        return None
    return html.escape("./" + quote(rel.encode("utf-8", "surrogateescape")), quote=True)


CARD_MIN = 540   # px: the card of a scan without a thumbnail; thumbnails show at their own width


def png_size(path: str | None) -> tuple[int, int] | None:
    """(width, height) of a PNG from its header, or None when it is not a readable PNG."""
    try:
        with open(str(path), "rb") as f:
            head = f.read(24)
    except (OSError, TypeError, ValueError):
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    w, h = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    return (w, h) if 0 < w <= 65536 and 0 < h <= 65536 else None


def _img(path: str | None, output_dir: Path, alt: str) -> str | None:
    """An ``<img>`` of the PNG ``path`` shown at its own size (a relative link), or None."""
    src = _rel(path, output_dir)
    if src is None:
        return None
    size = png_size(path)
    dims = f' width="{size[0]}" height="{size[1]}"' if size else ""
    return f'<img src="{src}"{dims} alt="{html.escape(alt, quote=True)}">'


THUMBNAILS_NOTE = ("Thumbnails: the whole model before and after; under it, when the edit "
                   "changed only a small part of it, a close-up of that part (the points that "
                   "moved) from the same direction.")
CLOSEUP_NOTE = ("changed part: the points that moved (handle and free region), framed alone "
                "from the same direction; nearer geometry cut away")


def _html(output_dir: Path, rows: list[dict[str, Any]], summary: dict[str, Any]) -> str:
    cards = []
    for row in rows:
        img = _img(row.get("png"), output_dir, f"before/after {row['scan']}") \
            or '<div class="noimg">no thumbnail</div>'
        close = _img(row.get("closeup"), output_dir, f"changed part before/after {row['scan']}")
        if close is not None:
            img += f'<div class="sub">{html.escape(CLOSEUP_NOTE)}</div>{close}'
        t = row.get("timings") or {}
        figures = (f"points {_fmt(row.get('points'), ',')} · "
                   f"centers {_fmt(row.get('centers'), 'd')}"
                   f"<br>residual {_fmt(row.get('residual'), '.3g')} · max constraint error "
                   f"{_fmt(row.get('constraint_error_rel'), '.2e')} of the diagonal"
                   f"<br>fit {_fmt(t.get('fit'), '.2f')} s · basis {_fmt(t.get('basis'), '.2f')} s"
                   f" · total {_fmt(row.get('seconds'), '.2f')} s")
        err = (f'<div class="err">{html.escape(row["error"])}</div>' if row.get("error") else "")
        if row.get("converged") is False:
            err += ('<div class="warn">fit not converged: largest constraint error above '
                    'fit.tolerance at fit.max_centers</div>')
        out = _rel(row.get("output"), output_dir)
        link = f' · <a href="{out}">model</a>' if out else ""
        flag = " unconverged" if row.get("converged") is False else ""
        status = html.escape(str(row["status"]))
        cards.append(f'<div class="card {status}{flag}"><h3>{html.escape(row["scan"])}</h3>'
                     f'<div class="status">{status}{link}</div>{img}'
                     f'<div class="fig">{figures}</div>{err}</div>')
    counts = summary.get("counts", {})
    head = " · ".join(f"{k} {v}" for k, v in counts.items())
    title = html.escape(str(summary.get("batch")))
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>splatdeform batch {title}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; background: #fafafa; }}
.grid {{ display: flex; flex-wrap: wrap; gap: 1em; }}
.card {{ background: white; border: 1px solid #ccc; border-radius: 6px;
  padding: .6em; width: fit-content; min-width: {CARD_MIN}px; max-width: 100%;
  box-sizing: border-box; }}
.card h3 {{ margin: 0 0 .3em 0; font-size: 1em; word-break: break-all; }}
.card img {{ display: block; max-width: 100%; height: auto; }}
.failed {{ border-color: #c33; }} .failed .status {{ color: #c33; font-weight: bold; }}
.skipped .status {{ color: #777; }} .ok .status {{ color: #282; }}
.err {{ color: #c33; font-family: monospace; font-size: .85em; }}
.unconverged {{ border-color: #d80; }} .warn {{ color: #b60; font-size: .85em; }}
.fig {{ font-size: .85em; color: #333; }} .noimg {{ color: #999; padding: 2em; }}
.sub {{ font-size: .8em; color: #555; margin: .4em 0 .2em 0; }}
</style></head><body>
<h1>splatdeform batch: {html.escape(str(summary.get('batch')))}</h1>
<p>{html.escape(head)} · {_fmt(summary.get('seconds'), '.1f')} s · config hash per scan in
<code>&lt;output&gt;.json</code> · <a href="report.csv">report.csv</a> ·
<a href="report.json">report.json</a></p>
<p class="sub">{html.escape(THUMBNAILS_NOTE)}</p>
<div class="grid">
{chr(10).join(cards)}
</div></body></html>
"""
