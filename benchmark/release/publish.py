"""``skidbench publish <dataset> <dir>``: a dataset's boards as a static web page a lab can put online as it
is (no server, nothing fetched: the CSS, the script and the figures are inline, and the page's
Content-Security-Policy forbids loading anything else).

``<dir>/<dataset>/index.html`` shows, per input protocol evaluated (benchmark/board/boards.py: the rows
compare
ranks, external rows of ``skidbench score`` included): the leaderboard (mean over terrains, compare's
``summary_table``: with the runs' per-window tables, every mean with its 95 % interval, ranked by
``rank_by`` under the ranking rule, the floor's row and the paper's claim per terrain; docs/intervals.md),
every (model, terrain) row with its CV and LD numbers (compare's ``detail_table``;
bootstrap intervals when the runs logged them), each row's provenance and the command that reproduces it,
and Figs. 3/4 of that protocol; then the figures of the dataset's last ``compare`` report
(benchmark/report/figures.py: Figs. 5-7, the wheel response, calibration curves), the dataset card, and how to
get the data (its bundle, when it was imported from one) and reproduce the page. Next to it,
``board-<protocol>.csv`` holds the numbers shown. ``<dir>/index.html`` lists every dataset published in
``<dir>``. Every number cell carries its full value in ``data-value`` (the text is rounded to 0.01).
"""

from __future__ import annotations

import base64
import datetime as dt
import html
import json
import re
import tempfile
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path
from string import Template
from typing import Any

import numpy as np
import pandas as pd

from skidbench.benchmark.board import boards as brd
from skidbench.benchmark.board import compare as cmp
from skidbench.benchmark.board import tables
from skidbench.benchmark.report import compare_figures, markdown
from skidbench.benchmark.report import figures as figs
from skidbench.benchmark.scoring import intervals as iv
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring import standings as st
from skidbench.benchmark.tracking import store as trk
from skidbench.pipeline.core.errors import SkidbenchError
from skidbench.pipeline.core.io import write_text_atomic
from skidbench.pipeline.core.layout import Layout
from skidbench.pipeline.datasets.imported import RECORD_DIR
from skidbench.pipeline.runner import environment

PROTOCOL_TITLES = {
    "commanded": "commanded: the commanded wheel rates (the paper's protocol)",
    "response": "response: the commands through the identified wheel response",
    "measured": "measured: the encoders' wheel rates (an oracle)",
}
#: compare's figures (reports/), in page order, with their captions
REPORT_FIGURES = (
    (
        "fig5_residual_vs_acceleration.png",
        "Fig. 5: yaw-rate residual of the full linear model vs angular acceleration",
    ),
    (
        "fig6_yaw_rate_surfaces.png",
        "Fig. 6: the friction-based model's yaw rate over the wheel-velocity plane",
    ),
    ("fig7_trajectories.png", "Fig. 7: true and predicted 6 s trajectories"),
    ("fig_protocols.png", "The input protocols side by side"),
    ("fig_wheel_response.png", "The identified wheel response against the encoders"),
    ("calibration.png", "Calibration of the predicted pose uncertainty"),
)
SITE_RECORD = "site.json"


class PublishError(SkidbenchError):
    pass


@dataclass
class PublishResult:
    page: Path
    index: Path
    bytes: int
    protocols: list[str] = field(default_factory=list)
    figures: int = 0


def esc(v: Any) -> str:
    return html.escape(str(v), quote=True)


# -- Markdown (the dataset card, compare's tables) to HTML: headings, tables, lists, paragraphs, code --
def _inline(text: str) -> str:
    out = esc(text)
    out = re.sub(r"`([^`]+)`", r"<code>\1</code>", out)
    out = re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", out)
    return out


def markdown_html(md: str) -> str:
    """The Markdown subset skidbench writes (card.md, report tables) as HTML."""
    lines = md.splitlines()
    out: list[str] = []
    i = 0
    while i < len(lines):
        ln = lines[i]
        if ln.startswith("```"):
            j = i + 1
            while j < len(lines) and not lines[j].startswith("```"):
                j += 1
            out.append("<pre>" + esc("\n".join(lines[i + 1 : j])) + "</pre>")
            i = j + 1
            continue
        m = re.match(r"^(#{1,6})\s+(.*)", ln)
        if m:
            level = min(len(m.group(1)) + 2, 6)  # the page has h1/h2 of its own
            out.append(f"<h{level}>{_inline(m.group(2))}</h{level}>")
        elif ln.startswith("|"):
            rows = []
            while i < len(lines) and lines[i].startswith("|"):
                rows.append(
                    [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", lines[i].strip())[1:-1]]
                )
                i += 1
            body = [r for r in rows[1:] if not all(re.fullmatch(r":?-+:?", c) for c in r)]
            head = "".join(f"<th>{_inline(c)}</th>" for c in rows[0])
            trs = "".join("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in r) + "</tr>" for r in body)
            out.append(f"<table><thead><tr>{head}</tr></thead><tbody>{trs}</tbody></table>")
            continue
        elif re.match(r"^\s*[-*] ", ln):
            items = []
            while i < len(lines) and re.match(r"^\s*[-*] ", lines[i]):
                item = re.sub(r"^\s*[-*] ", "", lines[i])
                items.append(f"<li>{_inline(item)}</li>")
                i += 1
            out.append("<ul>" + "".join(items) + "</ul>")
            continue
        elif ln.strip():
            para = [ln]
            while (
                i + 1 < len(lines)
                and lines[i + 1].strip()
                and not re.match(r"^(#|\||```|\s*[-*] )", lines[i + 1])
            ):
                i += 1
                para.append(lines[i])
            out.append(f"<p>{_inline(' '.join(para))}</p>")
        i += 1
    return "\n".join(out)


# -- tables ---------------------------------------------------------------------------------------------
def _cell(v: Any, digits: int = 2) -> str:
    """A table cell: numbers right-aligned, shown to ``digits`` decimals, full value in data-value."""
    if isinstance(v, bool | np.bool_):
        return f"<td>{'yes' if v else ''}</td>"
    if isinstance(v, int | np.integer):
        return f'<td class="num" data-value="{int(v)}">{int(v)}</td>'
    if isinstance(v, float | np.floating):
        if not np.isfinite(v):
            return '<td class="num" data-value="">n/a</td>'
        return f'<td class="num" data-value="{float(v)!r}">{float(v):.{digits}f}</td>'
    return f"<td>{esc(v)}</td>"


def html_table(df: pd.DataFrame, cls: str = "sortable", row_classes: list[str] | None = None,
               data: list[dict[str, str]] | None = None) -> str:  # fmt: skip
    head = "".join(f"<th>{esc(c)}</th>" for c in df.columns)
    body = []
    for k, row in enumerate(df.itertuples(index=False)):
        rc = f' class="{row_classes[k]}"' if row_classes and row_classes[k] else ""
        attrs = "".join(f' data-{a}="{esc(v)}"' for a, v in (data[k] if data else {}).items())
        body.append(f"<tr{rc}{attrs}>" + "".join(_cell(v) for v in row) + "</tr>")
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table>'


def interval_columns(rows: pd.DataFrame, horizon: float) -> dict[str, tuple[str, str, str]]:
    """``{metric column: (low column, high column, label)}`` of the 95 % intervals the runs logged
    (``<metric key>_ci_lo``/``_ci_hi``, docs/intervals.md), for every metric of the registry that has them."""
    from skidbench.benchmark.scoring import metrics as mt

    out = {}
    for m in mt.METRICS:
        for split in tables.SPLITS:
            c = m.metric_key(split, horizon)
            lo, hi = f"{c}_ci_lo", f"{c}_ci_hi"
            if lo in rows and hi in rows and pd.to_numeric(rows[lo], errors="coerce").notna().any():
                out[c] = (lo, hi, f"{m.column_label(split)} 95% interval")
    return out


def _rows_table(board: brd.Board, standings: st.Standings | None = None) -> str:
    """Every (model, terrain) row: compare's detail table (with ``standings``: the terrain's aggregate, rank,
    standing and floor), the intervals when logged (``a to b``, in place of the bounds' own columns),
    external marks."""
    rows = board.rows
    detail = tables.detail_table(rows, board.horizon, standings)
    detail = detail.drop(columns=["inputs", "run", "reason"], errors="ignore")
    for lo, hi, label in interval_columns(rows, board.horizon).values():
        los, his = pd.to_numeric(rows[lo], errors="coerce"), pd.to_numeric(rows[hi], errors="coerce")
        base = label.removesuffix(" 95% interval")
        detail = detail.drop(columns=[f"{base} lo", f"{base} hi"], errors="ignore")
        at = list(detail.columns).index(base) + 1 if base in detail else len(detail.columns)
        detail.insert(at, label, [  # beside its value
            f"{a:.2f} to {b:.2f}" if np.isfinite(a) and np.isfinite(b) else ""
            for a, b in zip(los, his, strict=True)
        ])  # fmt: skip
    for c in [c for c in detail.columns if c.endswith(" blocks")]:  # counts, not measurements
        detail[c] = [int(v) if np.isfinite(v) else "" for v in pd.to_numeric(detail[c], errors="coerce")]
    external = rows["external"] if "external" in rows else pd.Series(False, index=rows.index)
    classes = [
        " ".join(c for c in ("external" if bool(e) else "", "failed" if s != "FINISHED" else "") if c)
        for e, s in zip(external, rows["status"], strict=True)
    ]
    data = [
        {"model": m, "terrain": t, "run": r}
        for m, t, r in zip(rows["model"], rows["terrain"], rows["run_id"], strict=True)
    ]
    return html_table(detail, row_classes=classes, data=data)


def _provenance_table(board: brd.Board) -> str:
    rows = board.rows
    keep = ["model", "terrain", "status", "version", "package", "run_id", "parent_run_id", "git_commit",
            "start_time_utc", "splits_fingerprint", "predictions_sha256"]  # fmt: skip
    df = rows[[c for c in keep if c in rows]].copy()
    for c in ("run_id", "parent_run_id", "git_commit", "splits_fingerprint", "predictions_sha256"):
        if c in df:
            df[c] = df[c].fillna("").astype(str).str[:12]
    classes = ["external" if bool(e) else "" for e in rows.get("external", [False] * len(rows))]
    parts = [html_table(df, row_classes=classes)]
    cmds = []
    for r in rows.to_dict("records"):
        if r.get("reproduce"):
            cmds.append(f"# {r['model']} on {r['terrain']} (run {str(r['run_id'])[:8]})\n{r['reproduce']}")
    if cmds:
        parts.append("<details><summary>How to reproduce each row</summary><pre>" + esc("\n\n".join(cmds))
                     + "</pre></details>")  # fmt: skip
    return "\n".join(parts)


# -- figures ---------------------------------------------------------------------------------------------
def png_data_uri(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(Path(path).read_bytes()).decode("ascii")


def _figure(path: Path, caption: str) -> str:
    return (f'<figure><img alt="{esc(caption)}" src="{png_data_uri(path)}"><figcaption>{esc(caption)}'
            "</figcaption></figure>")  # fmt: skip


def _protocol_figures(board: brd.Board, tmp: Path, dpi: int, standings: st.Standings | None) -> list[str]:
    out = []
    ok = board.rows
    for m in (m for m in mt.METRICS if m.figure is not None):  # Figs. 3, 4 and every metric with a figure
        path = tmp / f"{Path(m.figure.file).stem}_{board.protocol}.png"
        figs.metric_bars(
            ok, m, board.horizon, tables.SPLITS, path, dpi, compare_figures.floor_of(standings, m)
        )
        out.append(_figure(path, f"{m.figure.caption} (inputs={board.protocol})"))
    return out


# -- the page --------------------------------------------------------------------------------------------
def _facts(items: dict[str, Any]) -> str:
    return '<dl class="facts">' + "".join(
        f"<dt>{esc(k)}</dt><dd>{v}</dd>" for k, v in items.items() if v not in (None, "")
    ) + "</dl>"  # fmt: skip


def leaderboard_html(board: brd.Board, standings: st.Standings | None) -> str:
    """The protocol's leaderboard as compare ranks it (docs/intervals.md): with ``standings`` (the runs'
    per-window tables were found), every mean over terrains with its 95 % interval, ranked by the
    aggregate under the ranking rule (best only when resolved from every other, else tied; too few blocks:
    not ranked, with the reason), the floor's row, who leads and the paper's claim per terrain and overall;
    without, the means listed by LD translational RMSRE and said not to be a ranking."""
    if standings is None:
        summary = tables.summary_table(board.rows, board.horizon, "ld_trans").drop(columns="rank")
        return (
            "<h3>Leaderboard (mean over terrains)</h3><p class='note'>The runs' per-window tables are not "
            "here, so no paired comparison: listed by LD translational RMSRE, not ranked; read the rows' "
            "intervals below.</p>" + html_table(summary)
        )
    summary = tables.summary_table(board.rows, board.horizon, standings.ranked_by, standings)
    claim = "".join(
        f"<li>{esc(scope)}: {esc(verdict)}</li>" for scope, (verdict, _) in standings.claim.items()
    )
    ranked = markdown.ranked_by_line(standings.ranked_by, board.horizon, standings)
    return (
        "<h3>Leaderboard (mean over terrains; estimate [95 % interval])</h3>"
        f"<p class='note'>{_inline(ranked[2:])}. "
        "The floor is not a model: the simulator's exact velocities against this ground truth.</p>"
        + html_table(summary)
        + f"<p><strong>{esc(standings.verdicts.get('overall', ''))}</strong></p>"
        + (f"<p>The paper's claim (friction-based best on LD, comparable on CV):</p><ul>{claim}</ul>"
           if claim else "")
    )  # fmt: skip


@dataclass(frozen=True)
class PublishSettings:
    """What ``publish`` reads of its config: whether the page has figures (``publish.figures``) and their
    ``publish.dpi``, and how the boards are ranked (``rank_by``, ``intervals``), as compare ranks them."""

    figures: bool
    dpi: int
    rank_by: str = st.AGGREGATE
    intervals: iv.IntervalConfig = field(default_factory=iv.IntervalConfig)

    @classmethod
    def from_cfg(cls, cfg: Any) -> PublishSettings:
        return cls(
            bool(cfg.publish.figures),
            int(cfg.publish.dpi),
            str(cfg.get("rank_by") or st.AGGREGATE),
            iv.IntervalConfig.from_cfg(cfg),
        )


def _protocol_section(
    board: brd.Board, tmp: Path, settings: PublishSettings, standings: st.Standings | None = None
) -> str:  # fmt: skip
    s = board.settings
    n_ext = int(board.rows.get("external", pd.Series(dtype=bool)).sum())
    parts = [
        f'<section id="{board.protocol}">',
        f"<h2>Inputs {esc(PROTOCOL_TITLES.get(board.protocol, board.protocol))}</h2>",
        f"<p class='note'>{board.horizon:g} s horizon; RMSRE in % of the relative translational error "
        "(position error / distance travelled) and rotational error (|yaw error| / absolute rotation), lower "
        f"is better; windows under {esc(s.get('min_distance_m', '?'))} m or "
        f"{esc(s.get('min_rotation_deg', '?'))} deg are "
        f"left out of that error; <em>n</em>: windows. Models fitted per terrain on Train. From the evaluate "
        f"run <code>{esc(board.parent_run_id)}</code>"
        + (f" and {n_ext} external row(s) scored from a predictions file (<code>skidbench score</code>)"
           if n_ext else "")
        + ". A gap smaller than the rows' interval is a tie, not a ranking.</p>",
        leaderboard_html(board, standings),
        "<h3>Per terrain and test split</h3>",
        _rows_table(board, standings),
        "<h3>Provenance of each row</h3>",
        _provenance_table(board),
    ]  # fmt: skip
    if settings.figures:
        parts += _protocol_figures(board, tmp, settings.dpi, standings)
    parts.append("</section>")
    return "\n".join(parts)


def _dataset_facts(layout: Layout, rec: dict[str, Any], bundle_doc: dict[str, Any] | None) -> dict[str, str]:
    facts = {
        "dataset": f"<code>{esc(layout.dataset)}</code>",
        "source": esc(f"{rec.get('source')} ({rec.get('root')})"),
        "identity": f"<code>{esc(rec.get('fingerprint'))}</code>",
        "terrains": esc(", ".join(rec.get("terrains") or [])),
        "sequences": esc(rec.get("sequences")),
    }
    if bundle_doc:
        facts["licence of the data"] = esc(bundle_doc.get("licence"))
        facts["provenance"] = esc((bundle_doc.get("provenance") or {}).get("statement"))
        facts["robot"] = esc(bundle_doc["robot"]["name"])
        proto, metric = bundle_doc["protocol"], bundle_doc["metric"]
        facts["protocol / metric"] = esc(
            f"protocol version {proto['version']}, metric {metric['name']} version {metric['version']}"
        )
    return facts


def build_page(
    settings: PublishSettings, layout: Layout, rec: dict[str, Any], boards: dict[str, brd.Board], tmp: Path
) -> tuple[str, int]:
    from skidbench.benchmark.release.bundle import METRIC, read_bundle_doc

    bundle_doc = read_bundle_doc(layout.root / RECORD_DIR)
    nav = " ".join(f'<a href="#{p}">inputs={esc(p)}</a>' for p in boards)
    nav += (
        ' <a href="#figures">figures</a> <a href="#card">dataset card</a> <a href="#reproduce">reproduce</a>'
    )
    when = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    body = [
        f"<header><h1>skidbench: {esc(layout.dataset)}</h1>",
        "<p>6 s pose-prediction benchmark of skid-steer motion models (Rabiee &amp; Biswas, ICRA 2019 "
        "metric); "
        f"published {when} by skidbench {esc(environment.git_commit()[:12])}.</p></header>",
        f"<nav>{nav}</nav><main>",
        "<h2>The dataset</h2>",
        _facts(_dataset_facts(layout, rec, bundle_doc)),
        f"<p class='note'>Metric: {esc(METRIC['definition'])}.</p>",
    ]
    for b in boards.values():
        standings = cmp.standings_of(settings.rank_by, settings.intervals, layout, b.rows, b.protocol,
                                     b.horizon, [])  # fmt: skip
        body.append(_protocol_section(b, tmp, settings, standings))
    n_fig = 0
    figs_html = []
    if settings.figures:
        for name, caption in REPORT_FIGURES:
            path = layout.reports / name
            if path.is_file():
                figs_html.append(_figure(path, caption))
                n_fig += 1
    body.append('<section id="figures"><h2>Figures of the last compare report</h2>')
    body += figs_html or ["<p class='note'>No figures: run <code>skidbench compare</code> first.</p>"]
    body.append("</section>")
    card = layout.splits / "card.md"
    body.append('<section id="card" class="card"><h2>Dataset card</h2>')
    body.append(markdown_html(card.read_text()) if card.is_file() else "<p class='note'>No card.</p>")
    body.append("</section>")
    body.append(_reproduce_section(layout, rec, boards, bundle_doc))
    body.append("</main>")
    template = Template((files("skidbench.benchmark") / "publish_template.html").read_text())
    page = template.substitute(title=esc(f"skidbench: {layout.dataset}"), body="\n".join(body))
    return page, n_fig + (2 * len(boards) if settings.figures else 0)


def _reproduce_section(layout: Layout, rec: dict[str, Any], boards: dict[str, brd.Board], bundle_doc) -> str:
    ds = layout.dataset
    if bundle_doc:
        robot = bundle_doc["robot"]["name"]
        sel = f"source=bundle dataset={ds}" + (f" robot={robot}" if robot != "jackal" else "")
        get = [f"skidbench import <the bundle folder>      # verifies every sha256, makes dataset {ds}"]
    else:
        sel = "<the same source settings>"
        if rec.get("source") == "sim":
            m = re.fullmatch(r"sim-(\w+?)(?:-seed(\d+))?", ds)
            sel = f"scale={m.group(1)} seed={m.group(2) or 0}" if m else sel
            scale = m.group(1) if m else "<scale>"
            get = [f"make reproduce SCALE={scale}    # simulate the dataset and run every stage"]
        else:
            get = [f"skidbench export {ds} <dir>      # the bundle of this dataset, to download and import"]
    cmds = [*get]
    for p in boards:
        cmds.append(f"skidbench evaluate {sel}" + ("" if p == "commanded" else f" inputs={p}"))
    cmds += [f"skidbench compare {sel}", f"skidbench publish {ds} <dir>"]
    return (
        '<section id="reproduce"><h2>Reproduce this page</h2><pre>' + esc("\n".join(cmds)) + "</pre>"
        "<p class='note'>Each row's own commands are under its board's provenance.</p></section>"
    )


def write_index(site: Path) -> Path:
    """``<site>/index.html``: every dataset published in ``site`` (its ``<dataset>/site.json``)."""
    entries = []
    for rec_path in sorted(site.glob(f"*/{SITE_RECORD}")):
        try:
            entries.append(json.loads(rec_path.read_text()))
        except (OSError, ValueError):
            continue
    cells = [
        [f'<a href="{esc(e["dataset"])}/index.html">{esc(e["dataset"])}</a>', esc(e.get("source")),
         esc(", ".join(e.get("terrains") or [])), esc(", ".join(e.get("protocols") or [])),
         esc(e.get("published_utc"))]
        for e in entries
    ]  # fmt: skip
    rows = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in cells)
    head = "".join(f"<th>{h}</th>" for h in ("dataset", "source", "terrains", "protocols", "published"))
    body = (
        "<header><h1>skidbench benchmarks</h1><p>Every dataset published here.</p></header><main>"
        f'<table class="sortable"><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table></main>'
    )
    template = Template((files("skidbench.benchmark") / "publish_template.html").read_text())
    path = site / "index.html"
    write_text_atomic(path, template.substitute(title="skidbench benchmarks", body=body))
    return path


def publish(
    settings: PublishSettings, layout: Layout, rec: dict[str, Any], tracker: trk.Tracker, site: Path
) -> PublishResult:
    """Writes ``<site>/<dataset>/index.html`` (and the board CSVs, ``site.json``) and
    ``<site>/index.html``."""
    boards = brd.all_boards(tracker)
    if not boards:
        raise PublishError(
            f"{layout.root}: no `skidbench evaluate` run of dataset {layout.dataset} in {tracker.uri}; "
            "run it first"
        )
    site = Path(site).expanduser().absolute()
    out = site / layout.dataset
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="skidbench-publish-") as tmp:
        page, n_fig = build_page(settings, layout, rec, boards, Path(tmp))
    for b in boards.values():
        write_text_atomic(out / f"board-{b.protocol}.csv", b.rows.to_csv(index=False))
    path = out / "index.html"
    write_text_atomic(path, page)
    site_rec = {
        "dataset": layout.dataset,
        "source": rec.get("source"),
        "terrains": rec.get("terrains") or [],
        "protocols": list(boards),
        "published_utc": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M"),
    }
    write_text_atomic(out / SITE_RECORD, json.dumps(site_rec, indent=2) + "\n")
    index = write_index(site)
    return PublishResult(path, index, len(page.encode()), list(boards), n_fig)


def describe(res: PublishResult) -> str:
    return (
        f"publish: {res.page} ({res.bytes / 1e6:.2f} MB, boards {', '.join(res.protocols)}, "
        f"{res.figures} figures inline); site index {res.index}"
    )
