"""``skidbench publish <dataset> <dir>``: a dataset's boards as a static web page a lab can put online as it
is (no server, nothing fetched: the CSS, the script and the figures are inline, and the page's
Content-Security-Policy forbids loading anything else).

``<dir>/<dataset>/index.html`` is titled from the dataset's card (``publish.title`` to change it) and
shows, per input protocol evaluated (benchmark/board/boards.py: the entries compare ranks, the external
ones of ``skidbench score`` included), the compact board of benchmark/release/page.py (rank, method
linked to its paper or code, the ranking aggregate and the four RMSREs with their 95 % intervals,
submitter, date; each row expanding to its per-terrain cells and provenance), who leads under the ranking
rule and the paper's claim (docs/intervals.md), Figs. 3/4 of that protocol; then the dataset's card (robot,
terrains, sequences and durations, licence, provenance, where to get its public half), the methods,
how to submit, the figures of the dataset's last ``compare`` and how to reproduce the page. Whether the
test truth is withheld (scored by the maintainer) or public (entries self-reported) is said at the top.
Next to it, ``board-<protocol>.csv`` holds the numbers shown. ``<dir>/index.html`` lists every dataset
published in ``<dir>``. Nothing written names a file or folder of the publishing machine.
"""

from __future__ import annotations

import base64
import datetime as dt
import html
import json
import re
import sys
import tempfile
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path
from string import Template
from typing import Any

from skidbench.benchmark.board import boards as brd
from skidbench.benchmark.board import compare as cmp
from skidbench.benchmark.board.selection import results_of
from skidbench.benchmark.board.tables import scope_line
from skidbench.benchmark.release import halves as hv
from skidbench.benchmark.release import page as pg
from skidbench.benchmark.release.settings import PublishOptions
from skidbench.benchmark.report import compare_figures as cfigs
from skidbench.benchmark.report import figures as figs
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring import standings as st
from skidbench.benchmark.scoring.settings import IntervalConfig
from skidbench.benchmark.tracking import store as trk
from skidbench.pipeline.core.errors import SkidbenchError
from skidbench.pipeline.core.io import write_text_atomic
from skidbench.pipeline.core.layout import Layout
from skidbench.pipeline.core.manifest import Manifest
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
esc = pg.esc


class PublishError(SkidbenchError):
    pass


@dataclass
class PublishResult:
    page: Path
    index: Path
    bytes: int
    protocols: list[str] = field(default_factory=list)
    figures: int = 0


@dataclass(frozen=True)
class PublishSettings:
    """What ``publish`` reads of its config: the ``publish`` section (:class:`~skidbench.benchmark.release.
    settings.PublishOptions`: figures, dpi, title, download) and how the boards are ranked (``rank_by``,
    ``intervals``, as compare ranks them). The publish app makes it, reading each once."""

    page: PublishOptions = field(default_factory=PublishOptions)
    rank_by: str = st.AGGREGATE
    intervals: IntervalConfig = field(default_factory=IntervalConfig)


# -- figures ---------------------------------------------------------------------------------------------
def png_data_uri(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(Path(path).read_bytes()).decode("ascii")


def _figure(path: Path, caption: str) -> str:
    return (
        f'<figure><img alt="{esc(caption)}" src="{png_data_uri(path)}"><figcaption>{esc(caption)}'
        "</figcaption></figure>"
    )


def _protocol_figures(board: brd.Board, tmp: Path, dpi: int, standings: st.Standings | None) -> list[str]:
    out = []
    for m in (m for m in mt.METRICS if m.figure is not None):  # Figs. 3, 4 and every metric with a figure
        path = tmp / f"{Path(m.figure.file).stem}_{board.protocol}.png"
        figs.metric_bars(board.rows, m, board.horizon, pg.SPLITS, path, dpi, cfigs.floor_of(standings, m))
        out.append(_figure(path, f"{m.figure.caption} (inputs={board.protocol})"))
    return out


# -- the page --------------------------------------------------------------------------------------------
def _facts(items: dict[str, Any]) -> str:
    return (
        '<dl class="facts">'
        + "".join(f"<dt>{esc(k)}</dt><dd>{v}</dd>" for k, v in items.items() if v not in (None, ""))
        + "</dl>"
    )


def _protocol_section(
    board: brd.Board, tmp: Path, settings: PublishSettings, standings: st.Standings | None = None
) -> str:
    s = board.settings
    rule = (
        "Ranked by the aggregate under the ranking rule: a gap smaller than its interval is a tie; "
        "<em>best</em> only when resolved from every other entry."
        if standings is not None
        else "The runs' per-window tables are not here, so no paired comparison: listed by LD translational "
        "RMSRE, not ranked."
    )
    parts = [
        f'<section id="{board.protocol}">',
        f"<h2>Inputs {esc(PROTOCOL_TITLES.get(board.protocol, board.protocol))}</h2>",
        f"<p class='note'>{board.horizon:g} s horizon; RMSRE in % (lower is better), each the mean over "
        f"terrains with its 95 % interval; windows under {esc(s.get('min_distance_m', '?'))} m or "
        f"{esc(s.get('min_rotation_deg', '?'))} deg are left out of that error. {rule} "
        "<kbd>+</kbd> opens an entry's details.</p>",
        pg.board_table(board, standings),
    ]
    if standings is not None:
        claim = "".join(f"<li>{esc(scope)}: {esc(v)}</li>" for scope, (v, _) in standings.claim.items())
        parts.append(f"<p><strong>{esc(standings.verdicts.get('overall', ''))}</strong></p>")
        if scope := scope_line(standings):  # what the intervals cover: within this drive, or over drives
            parts.append(f"<p class='note scope'>{esc(scope)}</p>")
        if claim:
            parts.append(
                "<details><summary>The paper's claim (friction-based best on LD, comparable on CV)"
                f"</summary><ul>{claim}</ul></details>"
            )
    if settings.page.figures:
        parts.append(
            "<details><summary>Figures 3 and 4 (per terrain, with the floor)</summary>"
            + "".join(_protocol_figures(board, tmp, settings.page.dpi, standings))
            + "</details>"
        )
    parts.append("</section>")
    return "\n".join(parts)


def truth_status(layout: Layout) -> tuple[str, str]:
    """(release, sentence): whether this dataset's test truth is withheld or public, from its bundle (an
    imported dataset) or its last export (``<ds>/release.json``)."""
    from skidbench.benchmark.release.bundle import read_bundle_doc, release_of

    doc = read_bundle_doc(layout.root / RECORD_DIR)
    release = release_of(doc) if doc else None
    if release is None:
        try:
            release = json.loads((layout.root / hv.RELEASE_RECORD).read_text()).get("release")
        except (OSError, ValueError):
            release = hv.WITHHELD
    if release == hv.OPEN:
        return release, (
            "The test ground truth is public (an open release): submitted entries are self-reported."
        )
    return hv.WITHHELD, (
        "The CV/LD ground truth is withheld: the maintainer scores every submitted entry "
        "from its predictions file."
    )


def _card_section(
    settings: PublishSettings,
    layout: Layout,
    rec: dict[str, Any],
    release: str,
    bundle_doc: dict[str, Any] | None,
    robot: Any,
) -> tuple[str, str]:
    """The dataset's card (benchmark/release/halves.py ``public_card``: what a release shows of it) with
    its provenance and where to get the public half; and the page's title (the card's, or
    ``publish.title``)."""
    from skidbench.benchmark.release.bundle import METRIC, SIMULATED_LICENCE

    doc = bundle_doc or {}
    lic = doc.get("licence") or (SIMULATED_LICENCE if rec.get("source") == "sim" else "see its provenance")
    card = hv.public_card(layout, Manifest.read(layout.manifest), robot, release, lic)
    title = settings.page.title or card.splitlines()[0].lstrip("# ").strip()
    url = settings.page.download
    get = (
        f'<a href="{esc(url)}">{esc(url)}</a>, then <code>skidbench import &lt;its folder&gt;</code>'
        if url
        else "from the maintainer (<code>skidbench export</code> writes it), then <code>skidbench import "
        "&lt;its folder&gt;</code>"
    )
    facts = {
        "get the public half": get,
        "provenance": esc((doc.get("provenance") or {}).get("statement") or f"{rec.get('source')} data"),
        "identity": f"<code>{esc(rec.get('fingerprint'))}</code>",
        "protocol / metric": esc(
            f"input protocol version {(doc.get('protocol') or {}).get('version', 1)}, "
            f"metric {METRIC['name']} version {METRIC['version']}: {METRIC['definition']}"
        ),
    }
    body = pg.markdown_html("\n".join(card.splitlines()[1:]))
    return f'<section id="dataset" class="card"><h2>The dataset</h2>{body}{_facts(facts)}</section>', title


def _methods_section(boards: dict[str, brd.Board]) -> str:
    """Every built-in method on the boards (the anchor its name links to): what it is, from its code."""
    from skidbench.models.registry.plugins import discover

    infos = discover()
    names = sorted({str(m) for b in boards.values() for m in b.rows["model"]} & set(infos))
    items = []
    for name in names:
        cls = infos[name].cls
        doc = " ".join((cls.__doc__ or sys.modules[cls.__module__].__doc__ or "").split())
        doc = doc if len(doc) <= 300 else doc[: doc.rfind(". ", 0, 300) + 1] or doc[:300] + "..."
        items.append(
            f'<dt id="method-{esc(name)}">{esc(name)} <span class="note">version '
            f"{esc(infos[name].version)}, {esc(infos[name].package)}</span></dt>"
            f"<dd>{pg.inline(doc)}</dd>"
        )
    return (
        '<section id="methods"><h2>Built-in methods</h2><p class="note">Fitted per terrain on Train by '
        "skidbench itself; the floor is not a method (the ground truth's own velocities through the same "
        f'windows).</p><dl class="methods">{"".join(items)}</dl></section>'
    )


def _submit_section(ds: str, release: str) -> str:
    steps = [
        "Get the public half and <code>skidbench import</code> it.",
        "Fit your model on <code>splits/&lt;terrain&gt;/train/</code> (with its ground truth), run it on "
        "<code>inputs/&lt;protocol&gt;/&lt;terrain&gt;/&lt;cv|ld&gt;/*.parquet</code> and write one Parquet "
        "or CSV file: <code>sequence, t, vx, vy, wz</code> (m/s, m/s, rad/s), one row per input row.",
        f"Check it: <code>skidbench score {esc(ds)} --predictions &lt;file&gt; score.check=true</code>.",
        "Send it to the maintainer with the method's name, a link to its paper or code, who submits it and "
        "a one-line description; the same predictions are one entry."
        if release == hv.WITHHELD
        else "Score it: <code>skidbench score ... score.link=&lt;url&gt; score.submitter=&lt;who&gt;</code> "
        "(self-reported: the test truth is public).",
    ]
    return (
        '<section id="submit"><h2>Submit a method</h2><ol>'
        + "".join(f"<li>{s}</li>" for s in steps)
        + "</ol></section>"
    )


def _reproduce_section(layout: Layout, rec: dict[str, Any], boards: dict[str, brd.Board], bundle_doc) -> str:
    ds = layout.dataset
    if bundle_doc:
        robot = bundle_doc["robot"]["name"]
        sel = f"source=bundle dataset={ds}" + (f" robot={robot}" if robot != "jackal" else "")
        get = [
            f"skidbench import <public half> bundle.answers=<private half>   # the maintainer: dataset {ds}"
        ]
    elif rec.get("source") == "sim":
        m = re.fullmatch(r"sim-(\w+?)(?:-seed(\d+))?", ds)
        sel = f"scale={m.group(1)} seed={m.group(2) or 0}" if m else "<the same source settings>"
        get = [f"make reproduce SCALE={m.group(1) if m else '<scale>'}    # simulate it, run every stage"]
    else:
        sel = "<the same source settings>"
        get = [f"skidbench export {ds} <dir>      # the public and private halves of this dataset"]
    cmds = [
        *get,
        *[f"skidbench evaluate {sel}" + ("" if p == "commanded" else f" inputs={p}") for p in boards],
        f"skidbench compare {sel}",
        f"skidbench publish {ds} <dir>",
    ]
    return (
        '<section id="reproduce"><h2>Reproduce this page</h2><pre>' + esc("\n".join(cmds)) + "</pre>"
        "<p class='note'>Each entry's own command is in its details.</p></section>"
    )


def build_page(
    settings: PublishSettings, layout: Layout, rec: dict[str, Any], boards: dict[str, brd.Board], tmp: Path
) -> tuple[str, int]:
    from skidbench.benchmark.release.bundle import read_bundle_doc
    from skidbench.pipeline.core.robot import load_robot

    bundle_doc = read_bundle_doc(layout.root / RECORD_DIR)
    release, truth = truth_status(layout)
    robot = load_robot(str(Manifest.read(layout.manifest).robot or "jackal"))
    card, title = _card_section(settings, layout, rec, release, bundle_doc, robot)
    nav = " ".join(f'<a href="#{p}">inputs={esc(p)}</a>' for p in boards)
    nav += ' <a href="#dataset">dataset</a> <a href="#methods">methods</a> <a href="#submit">submit</a>'
    nav += ' <a href="#figures">figures</a> <a href="#reproduce">reproduce</a>'
    when = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    body = [
        f"<header><h1>{esc(title)}</h1>",
        "<p>A skidbench benchmark of skid-steer motion models: 6 s pose prediction, scored as Rabiee &amp; "
        f"Biswas (ICRA 2019). {esc(truth)}</p><p class='small'>Dataset <code>{esc(layout.dataset)}</code>; "
        f"published {when} by skidbench {esc(environment.git_commit()[:12])}.</p></header>",
        f"<nav>{nav}</nav><main>",
    ]
    for b in boards.values():
        pg.identity_columns(b.rows)
        standings = cmp.standings_of(
            settings.rank_by, settings.intervals, layout, b.rows, b.protocol, b.horizon, []
        )
        body.append(_protocol_section(b, tmp, settings, standings))
    body += [card, _methods_section(boards), _submit_section(layout.dataset, release)]
    figs_html = [
        _figure(layout.reports / n, c)
        for n, c in REPORT_FIGURES
        if settings.page.figures and (layout.reports / n).is_file()
    ]
    body.append('<section id="figures"><h2>Figures of the last compare report</h2>')
    body += figs_html or ["<p class='note'>No figures: run <code>skidbench compare</code> first.</p>"]
    body += ["</section>", _reproduce_section(layout, rec, boards, bundle_doc), "</main>"]
    template = Template((files("skidbench.benchmark.release") / "publish_template.html").read_text())
    page = template.substitute(title=esc(title), body="\n".join(body))
    return page, len(figs_html) + (2 * len(boards) if settings.page.figures else 0)


def write_index(site: Path) -> Path:
    """``<site>/index.html``: every dataset published in ``site`` (its ``<dataset>/site.json``)."""
    entries = []
    for rec_path in sorted(site.glob(f"*/{SITE_RECORD}")):
        try:
            entries.append(json.loads(rec_path.read_text()))
        except (OSError, ValueError):
            continue
    cells = [
        [
            f'<a href="{esc(e["dataset"])}/index.html">{esc(e.get("title") or e["dataset"])}</a>',
            esc(e.get("source")),
            esc(", ".join(e.get("terrains") or [])),
            esc(", ".join(e.get("protocols") or [])),
            esc(e.get("published_utc")),
        ]
        for e in entries
    ]
    rows = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in cells)
    head = "".join(f"<th>{h}</th>" for h in ("dataset", "source", "terrains", "protocols", "published"))
    body = (
        "<header><h1>skidbench benchmarks</h1><p>Every dataset published here.</p></header><main>"
        f'<table class="sortable"><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table></main>'
    )
    template = Template((files("skidbench.benchmark.release") / "publish_template.html").read_text())
    path = site / "index.html"
    write_text_atomic(path, template.substitute(title="skidbench benchmarks", body=body))
    return path


def publish(
    settings: PublishSettings, layout: Layout, rec: dict[str, Any], tracker: trk.Tracker, site: Path
) -> PublishResult:
    """Writes ``<site>/<dataset>/index.html`` (and the board CSVs, ``site.json``) and
    ``<site>/index.html``."""
    ident = tracker.dataset_id or rec.get("fingerprint")
    boards = brd.all_boards(results_of(layout, str(ident or "") or None, tracker.experiment_name))
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
        rows = b.rows.copy()
        for c in ("reproduce", "predictions"):
            if c in rows:
                rows[c] = rows[c].map(pg.public_text)
        write_text_atomic(out / f"board-{b.protocol}.csv", rows.to_csv(index=False))
    path = out / "index.html"
    write_text_atomic(path, page)
    title = re.search(r"<title>(.*?)</title>", page)
    site_rec = {
        "dataset": layout.dataset,
        "title": html.unescape(title.group(1)) if title else layout.dataset,
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
