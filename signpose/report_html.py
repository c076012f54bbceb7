"""``report.html`` beside a run's outputs and ``index.html`` in a batch folder.

Pages a person opens from disk or from a mail attachment: one static file
each, inline CSS, no script, no server; the plots are embedded as base64 PNG
(``data:`` URIs) and every link is relative to the page's own folder, so the
folder can be copied or mailed as it is.

``report.html`` is built from the run's ``report.json`` (metrics against the
ground truth, pose statuses, outliers, settings, versions, timing) and the
PNG plots beside it; keys it does not know are shown as they are, so new
numbers in report.json appear without a change here. ``index.html`` is built
from the batch's ``summary.csv``: one row per flight, its name linking to the
flight's ``report.html`` where the flight got that far.
"""

from __future__ import annotations

import base64
import csv
import html
import logging
import math
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from signpose.core.fileio import atomic_write
from signpose.io.results import read_report

log = logging.getLogger(__name__)
RUN_REPORT_NAME = "report.html"
INDEX_NAME = "index.html"
REPORT_JSON_NAME = "report.json"
SUMMARY_CSV_NAME = "summary.csv"
# The pipeline's plots, in reading order, with their captions; other PNGs follow by name.
PLOTS = (
    ("trajectory_3d.png", "Trajectory in 3D, coloured by time, with the signs"),
    ("views.png", "Top and side views; x, y, z over time with sigma bands"),
    ("errors.png", "Position and rotation error against the ground truth"),
    ("signs_per_frame.png", "Decoded map signs per frame"),
)
MAX_ROWS = 200  # rows of a long list (outliers) shown; report.json has them all
_STYLE = """
body { font-family: sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
th { background: #f0f0f0; }
.problem { color: #b42318; }
figure { margin: 1em 0; } img { max-width: 100%; border: 1px solid #ddd; }
details { margin: 0.5em 0 1.5em; }
"""


@dataclass(frozen=True)
class Link:
    """A table cell that links to ``href`` (relative to the page)."""

    text: str
    href: str


@dataclass(frozen=True)
class Figure:
    """A table cell holding a number already written as text (right-aligned)."""

    text: str


Cell = str | int | float | bool | None | Link | Figure


def _cell(value: Cell) -> str:
    if isinstance(value, Link):
        return f'<td><a href="{html.escape(value.href)}">{html.escape(value.text)}</a></td>'
    if isinstance(value, bool) or value is None:
        return f"<td>{'' if value is None else ('yes' if value else 'no')}</td>"
    if isinstance(value, int | float):
        return f'<td class="num">{html.escape(_number(value))}</td>'
    if isinstance(value, Figure):
        return f'<td class="num">{html.escape(value.text)}</td>'
    return f"<td>{html.escape(str(value))}</td>"


def _number(value: float) -> str:
    if isinstance(value, int):
        return str(value)
    return f"{value:.4g}" if math.isfinite(value) else ""


def _from_csv(text: str) -> Cell:
    """A summary.csv cell: numbers as they are written there, right-aligned; else the text."""
    try:
        float(text)
    except ValueError:
        return text
    return Figure(text)


def table(header: Iterable[str], rows: Iterable[Iterable[Cell]]) -> str:
    """An HTML table; cells are escaped, numbers right-aligned, ``Link`` cells linked."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(_cell(c) for c in row) + "</tr>\n" for row in rows)
    return f"<table>\n<tr>{head}</tr>\n{body}</table>\n"


def _records(records: list[Mapping], limit: int = MAX_ROWS) -> str:
    """A list of JSON objects as one table (columns: every key seen, in first-seen order)."""
    if not records:
        return "<p>none</p>\n"
    keys = list(dict.fromkeys(k for r in records for k in r))
    rows = [[_scalar(r.get(k)) for k in keys] for r in records[:limit]]
    more = len(records) - limit
    note = f"<p>... and {more} more in {REPORT_JSON_NAME}</p>\n" if more > 0 else ""
    return table(keys, rows) + note


def _scalar(value) -> Cell:
    if isinstance(value, list | dict):
        return ", ".join(map(str, value.values() if isinstance(value, dict) else value))
    return value


def _flatten(value, prefix: str = "") -> list[tuple[str, Cell]]:
    """Nested settings as ``(dotted.key, value)`` rows."""
    if isinstance(value, Mapping):
        rows = []
        for k, v in value.items():
            rows += _flatten(v, f"{prefix}.{k}" if prefix else str(k))
        return rows
    return [(prefix, _scalar(value))]


def _page(title: str, body: list[str]) -> str:
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{html.escape(title)}</title>\n<style>{_STYLE}</style>\n</head>\n<body>\n"
        + "".join(body)
        + "</body>\n</html>\n"
    )


def _pct(value) -> Cell:
    return Figure(f"{100 * value:.1f} %") if isinstance(value, int | float) else value


# --------------------------------------------------------------------------- report.html


def _head_section(name: str, report: Mapping) -> list[str]:
    pipe = report.get("pipeline") or {}
    out = [f"<h1>signpose run: {html.escape(name)}</h1>\n"]
    facts = [
        ("input", pipe.get("input")),
        ("input kind", pipe.get("input_kind")),
        ("frames", report.get("frames", pipe.get("frames"))),
        ("frames with signs", report.get("frames_with_signs")),
        ("frames per second", pipe.get("frames_per_second")),
        ("ground truth", (report.get("metrics") or {}).get("groundtruth")),
    ]
    out.append(table(["", ""], [[k, v] for k, v in facts if v is not None]))
    for line in pipe.get("problems") or []:
        out.append(f'<p class="problem">problem: {html.escape(str(line))}</p>\n')
    return out


def _metrics_section(report: Mapping) -> list[str]:
    """Per-method errors against the ground truth (every key report.json has)."""
    methods = (report.get("metrics") or {}).get("methods") or {}
    out = ["<h2>Metrics against the ground truth</h2>\n"]
    if not methods:
        return [*out, "<p>no ground truth given: nothing to compare with</p>\n"]
    columns: list[str] = []
    rows: dict[str, dict[str, Cell]] = {}
    for method, metrics in methods.items():
        row: dict[str, Cell] = {}
        for key, value in (metrics or {}).items():
            if isinstance(value, list) and len(value) == 3 and "_xyz" in key:
                # mae_xyz_m -> mae_x_m, mae_y_m, mae_z_m (the unit stays in the name)
                for axis, v in zip("xyz", value, strict=True):
                    row[key.replace("_xyz", f"_{axis}", 1)] = v
            else:
                row[key] = _scalar(value)
        columns += [c for c in row if c not in columns]
        rows[method] = row
    body = [[m, *(r.get(c) for c in columns)] for m, r in rows.items()]
    out.append(table(["method", *columns], body))
    out.append(
        "<p>Units in the names (_m metres, _deg degrees); coverage as a fraction of the "
        "frames.</p>\n"
    )
    return out


def _status_section(report: Mapping) -> list[str]:
    """Posed frames and the share of each pose status per method."""
    coverage = report.get("coverage") or {}
    out = ["<h2>Pose statuses</h2>\n"]
    if not coverage:
        return [*out, "<p>not recorded</p>\n"]
    tokens = list(dict.fromkeys(t for c in coverage.values() for t in (c.get("status") or {})))
    rows = []
    for method, c in coverage.items():
        shares = c.get("status") or {}
        counts = [c.get("frames"), c.get("posed"), _pct(c.get("coverage")), c.get("bridged")]
        rows.append([method, *counts, *(_pct(shares.get(t, 0.0)) for t in tokens)])
    out.append(table(["method", "frames", "posed", "coverage", "bridged frames", *tokens], rows))
    for method, c in coverage.items():
        if c.get("weak"):
            out.append(f"<details><summary>{html.escape(method)}: weak poses</summary>\n")
            out += [_records(c["weak"]), "</details>\n"]
    return out


def _outlier_section(report: Mapping) -> list[str]:
    """Rejected and down-weighted observations, refused readings."""
    o = report.get("outliers") or {}
    refused = ((report.get("pipeline") or {}).get("refused")) or {}
    out = ["<h2>Outliers</h2>\n"]
    counts = {f"rejected by {k}": v for k, v in (o.get("n_rejected") or {}).items()}
    counts["down-weighted keypoints"] = o.get("n_downweighted")
    counts |= {f"refused: {k}": v for k, v in (refused.get("counts") or {}).items()}
    out.append(table(["what", "count"], [[k, v] for k, v in counts.items() if v is not None]))
    lists = [
        ("rejected", o.get("rejected")),
        ("misdecoded", o.get("misdecoded")),
        ("unknown codes", o.get("unknown_codes")),
        ("refused readings", refused.get("observations")),
        ("baseline frames rejected", o.get("baseline_rejected")),
        ("down-weighted keypoints", o.get("downweighted")),
    ]
    for title, records in lists:
        if not records:
            continue
        records = [r if isinstance(r, Mapping) else {"value": r} for r in records]
        out.append(f"<details><summary>{html.escape(title)} ({len(records)})</summary>\n")
        out += [_records(records), "</details>\n"]
    return out


def _plots_section(out_dir: Path) -> list[str]:
    known = [name for name, _ in PLOTS]
    captions = dict(PLOTS)
    names = [n for n in known if (out_dir / n).is_file()]
    names += sorted(p.name for p in out_dir.glob("*.png") if p.name not in known)
    out = ["<h2>Plots</h2>\n"]
    if not names:
        return [*out, "<p>no plots (the run was given --no-plots)</p>\n"]
    for name in names:
        data = base64.b64encode((out_dir / name).read_bytes()).decode("ascii")
        caption = html.escape(captions.get(name, name))
        out.append(
            f'<figure><img src="data:image/png;base64,{data}" alt="{caption}">'
            f"<figcaption>{caption} ({html.escape(name)})</figcaption></figure>\n"
        )
    return out


def _settings_section(report: Mapping) -> list[str]:
    pipe = report.get("pipeline") or {}
    out = ["<h2>Settings and versions</h2>\n"]
    out.append(table(["package", "version"], (report.get("versions") or {}).items()))
    timing = pipe.get("timing_ms_per_frame") or {}
    if timing:
        out.append(table(["stage", "ms per frame"], timing.items()))
    settings = {"estimator": report.get("settings") or {}, "run": pipe.get("settings") or {}}
    if report.get("motion_prior"):
        settings["motion_prior"] = report["motion_prior"]
    out.append("<details><summary>every setting</summary>\n")
    out += [table(["setting", "value"], _flatten(settings)), "</details>\n"]
    return out


def _files_section(out_dir: Path) -> list[str]:
    files = sorted(
        p.name
        for p in out_dir.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.name != RUN_REPORT_NAME
    )
    rows = [[Link(n, n), (out_dir / n).stat().st_size] for n in files]
    return ["<h2>Files</h2>\n", table(["file", "bytes"], rows)]


def render_run_report(out_dir: str | os.PathLike, report: Mapping | None = None) -> str:
    """report.html's text for the run folder ``out_dir`` (report.json read when not given)."""
    out = Path(out_dir)
    if report is None:
        path = out / REPORT_JSON_NAME
        report = read_report(path) if path.is_file() else {}
    body = _head_section(out.resolve().name, report)
    for part in (_metrics_section, _status_section, _outlier_section):
        body += _guarded(part, report)
    body += _plots_section(out) + _guarded(_settings_section, report) + _files_section(out)
    return _page(f"signpose run: {out.resolve().name}", body)


def _guarded(part, report: Mapping) -> list[str]:
    """``part(report)``, or one line saying it could not be shown.

    report.json's sections grow with the estimator; a section in a form this
    page does not know must not cost the run its other outputs.
    """
    try:
        return part(report)
    except (AttributeError, KeyError, TypeError, ValueError) as exc:
        name = part.__name__.strip("_").removesuffix("_section")
        log.warning("report.html: %s section not shown: %s", name, exc)
        return [
            f"<h2>{html.escape(name)}</h2>\n",
            f'<p class="problem">not shown: report.json has it in a form this page does not '
            f"know ({html.escape(type(exc).__name__)}: {html.escape(str(exc))})</p>\n",
        ]


def write_run_report(out_dir: str | os.PathLike, report: Mapping | None = None) -> Path:
    """Write ``out_dir/report.html`` (atomically) and return its path."""
    path = Path(out_dir) / RUN_REPORT_NAME
    text = render_run_report(out_dir, report)
    with atomic_write(path, "w", encoding="utf-8") as f:
        f.write(text)
    return path


# --------------------------------------------------------------------------- index.html


def _summary_rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    if not path.is_file():
        return [], []
    with open(path, encoding="utf-8", newline="") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


def render_batch_index(out_dir: str | os.PathLike) -> str:
    """index.html's text for the batch folder ``out_dir``: every flight with its summary row."""
    out = Path(out_dir)
    header, rows = _summary_rows(out / SUMMARY_CSV_NAME)
    statuses = [r.get("status", "") for r in rows]
    tally = ", ".join(f"{statuses.count(s)} {s}" for s in dict.fromkeys(statuses)) or "no flights"
    body = [
        f"<h1>signpose batch: {html.escape(out.resolve().name)}</h1>\n",
        f"<p>{len(rows)} flights: {html.escape(tally)}. "
        f'The same rows as <a href="{SUMMARY_CSV_NAME}">{SUMMARY_CSV_NAME}</a>; '
        "a flight's name opens its report.</p>\n",
    ]
    cells = []
    for r in rows:
        flight = r.get("flight", "")
        report = f"{flight}/{RUN_REPORT_NAME}"
        first: Cell = Link(flight, report) if flight and (out / report).is_file() else flight
        cells.append([first, *(_from_csv(r.get(h) or "") for h in header if h != "flight")])
    body.append(table(["flight", *(h for h in header if h != "flight")], cells))
    return _page(f"signpose batch: {out.resolve().name}", body)


def write_batch_index(out_dir: str | os.PathLike) -> Path:
    """Write ``out_dir/index.html`` (atomically) and return its path."""
    path = Path(out_dir) / INDEX_NAME
    text = render_batch_index(out_dir)
    with atomic_write(path, "w", encoding="utf-8") as f:
        f.write(text)
    return path
