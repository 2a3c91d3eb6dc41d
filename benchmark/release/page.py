"""The published page's boards (benchmark/release/publish.py assembles the page): per input protocol one
compact table a reader of KITTI's board would recognise, one row per entry: its rank, the method linked to
its paper or code, the ranking aggregate with its 95 % interval, the four RMSREs (translational and
rotational, CV and LD, each the mean over terrains with its interval), the submitter and the date. Each row
expands (its button, the page's script) to its details: the per-terrain cells with their intervals and
window counts, the description, provenance (runs, code version and digest, the skidbench commit, the split
files' fingerprint, the predictions' sha256) and the command that reproduces it. Nothing in it names a file
of the publishing machine: a command's paths are its file names (:func:`public_text`)."""

from __future__ import annotations

import html
import re
from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from skidbench.benchmark.board import boards as brd
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring import standings as st
from skidbench.benchmark.scoring.floor import FLOOR

SPLITS = ("cv", "ld")
#: the built-in entries' submitter (evaluated by the maintainer with skidbench's own models)
BUILTIN = "skidbench (built-in model)"


def esc(v: Any) -> str:
    return html.escape(str(v), quote=True)


#: an absolute path of the publishing machine (POSIX or Windows) in a text, not a URL's
_PATH = re.compile(r"(?<![\w:/.~-])(?:/|~/|[A-Za-z]:\\)(?:[^\s'\"<>|;,/\\]+[/\\])*([^\s'\"<>|;,/\\]+)[/\\]?")


# -- Markdown (the dataset card, compare's tables) to HTML: headings, tables, lists, paragraphs, code --
def inline(text: str) -> str:
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
            out.append(f"<h{level}>{inline(m.group(2))}</h{level}>")
        elif ln.startswith("|"):
            rows = []
            while i < len(lines) and lines[i].startswith("|"):
                rows.append(
                    [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", lines[i].strip())[1:-1]]
                )
                i += 1
            body = [r for r in rows[1:] if not all(re.fullmatch(r":?-+:?", c) for c in r)]
            head = "".join(f"<th>{inline(c)}</th>" for c in rows[0])
            trs = "".join("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in r) + "</tr>" for r in body)
            out.append(f"<table><thead><tr>{head}</tr></thead><tbody>{trs}</tbody></table>")
            continue
        elif re.match(r"^\s*[-*] ", ln):
            items = []
            while i < len(lines) and re.match(r"^\s*[-*] ", lines[i]):
                item = re.sub(r"^\s*[-*] ", "", lines[i])
                items.append(f"<li>{inline(item)}</li>")
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
            out.append(f"<p>{inline(' '.join(para))}</p>")
        i += 1
    return "\n".join(out)


def public_text(text: Any) -> str:
    """``text`` with every absolute path replaced by its last part (``/home/me/out/p.parquet`` ->
    ``p.parquet``): a command, as a reader runs it in their own folder."""
    return _PATH.sub(lambda m: m.group(1), str(text or ""))


def _num(v: float, lo: float = np.nan, hi: float = np.nan) -> str:
    """A number cell: the value to 0.01 (full value in ``data-value``), its interval beneath."""
    if not np.isfinite(v):
        return '<td class="num" data-value="">n/a</td>'
    ci = f'<span class="ci">[{lo:.2f}, {hi:.2f}]</span>' if np.isfinite(lo) and np.isfinite(hi) else ""
    return f'<td class="num" data-value="{float(v)!r}">{float(v):.2f}{ci}</td>'


def _f(row: Mapping[str, Any], key: str) -> float:
    try:
        return float(row.get(key, np.nan))
    except (TypeError, ValueError):
        return np.nan


def entry_link(model: str, rows: pd.DataFrame) -> str:
    """The href of an entry: its submission's link (``skidbench score``), else the built-in model's
    description on this page."""
    link = str(rows["link"].iloc[0]) if "link" in rows and len(rows) and rows["link"].iloc[0] else ""
    return link if re.match(r"(https?://|doi:)", link) else f"#method-{model}"


def _href(link: str) -> str:
    return f"https://doi.org/{link[4:]}" if link.startswith("doi:") else link


def _headline_cells(r: Mapping[str, Any]) -> list[str]:
    return [
        _num(_f(r, f"{m.name}|{s}|estimate"), _f(r, f"{m.name}|{s}|lo"), _f(r, f"{m.name}|{s}|hi"))
        for s in SPLITS
        for m in mt.PAPER
    ]


def _mean_cells(g: pd.DataFrame, horizon: float) -> list[str]:
    """Without standings: the means over terrains of the four RMSREs, no interval."""
    out = []
    for s in SPLITS:
        for m in mt.PAPER:
            key = m.metric_key(s, horizon)
            v = pd.to_numeric(g[key], errors="coerce").to_numpy(float) if key in g else np.array([])
            out.append(_num(float(np.mean(v)) if len(v) and np.isfinite(v).all() else np.nan))
    return out


def board_table(board: brd.Board, standings: st.Standings | None) -> str:
    """The protocol's compact table (module docstring): entries in rank order, the floor last."""
    rows = board.rows
    labels = [m.column_label(s) for s in SPLITS for m in mt.PAPER]
    agg = (
        st.AGGREGATE_LABEL
        if standings is None or standings.ranked_by == st.AGGREGATE
        else f"{standings.ranked_by} %"
    )
    head = ["#", "Method", f"{agg} [95 %]", *labels, "Submitter", "Date"]
    order = _order(rows, standings)
    body = []
    for model in order:
        g = rows[rows["model"] == model]
        r = (
            standings.overall.set_index("model").loc[model]
            if standings is not None and model in set(standings.overall["model"])
            else pd.Series(dtype=object)
        )
        did = f"{board.protocol}-{re.sub(r'[^A-Za-z0-9_-]', '-', str(model))}"
        if model == FLOOR:
            name = (
                f'<span class="floor">{esc(model)}</span> <span class="note">(not a method: the ground '
                "truth's own velocities)</span>"
            )
            who, when = "", ""
        else:
            ext = " external" if "external" in g and g["external"].astype(bool).any() else ""
            name = (
                f'<button type="button" class="more" aria-expanded="false" aria-controls="{did}-more" '
                f'title="details">+</button> <a href="{esc(_href(entry_link(model, g)))}">{esc(model)}</a>'
                + (f' <span class="tag{ext}">submitted</span>' if ext else "")
            )
            who = esc(_first(g, "submitter") or BUILTIN)
            when = esc(_first(g, "submitted") or str(_first(g, "start_time_utc"))[:10])
        agg_cell = _num(_f(r, "estimate"), _f(r, "lo"), _f(r, "hi")) if len(r) else _num(np.nan)
        cells = _headline_cells(r) if len(r) else _mean_cells(g, board.horizon)
        rank = esc(r.get("rank", "")) if len(r) else ""
        standing = str(r.get("standing", "")) if len(r) else ""
        body.append(
            f'<tr class="entry" id="{did}" data-model="{esc(model)}" title="{esc(standing)}">'
            f"<td>{rank}</td><td>{name}</td>{agg_cell}{''.join(cells)}<td>{who}</td><td>{when}</td>"
            "</tr>"
        )
        if model != FLOOR:
            body.append(
                f'<tr class="more-row" id="{did}-more" hidden><td colspan="{len(head)}">'
                f"{entry_details(board, model, g, standing)}</td></tr>"
            )
    ths = "".join(f"<th>{esc(h)}</th>" for h in head)
    return f'<table class="board"><thead><tr>{ths}</tr></thead><tbody>{"".join(body)}</tbody></table>'


def _first(g: pd.DataFrame, col: str) -> str:
    if col not in g:
        return ""
    vals = [str(v) for v in g[col] if isinstance(v, str) and v and v != "nan"]
    return vals[0] if vals else ""


def _order(rows: pd.DataFrame, standings: st.Standings | None) -> list[str]:
    """The entries in rank order (the ranked first, by rank and estimate), then the rest, the floor last."""
    models = list(dict.fromkeys(str(m) for m in rows["model"]))
    if standings is None:
        key = mt.PAPER[0].metric_key("ld", 6.0)
        means = {
            m: pd.to_numeric(rows.loc[rows["model"] == m, key], errors="coerce").mean()
            if key in rows
            else np.nan
            for m in models
        }
        return sorted(models, key=lambda m: (not np.isfinite(means[m]), means[m]))
    ov = standings.overall
    keyed = sorted(
        (
            (
                0 if str(r).isdigit() else 1,
                int(r) if str(r).isdigit() else 0,
                float(e) if pd.notna(e) else np.inf,
                str(m),
            )
            for m, r, e in zip(ov["model"], ov["rank"], ov["estimate"], strict=True)
            if m != FLOOR
        )
    )
    ranked = [k[3] for k in keyed]
    tail = [FLOOR] if (ov["model"] == FLOOR).any() else []
    return [m for m in ranked if m in models] + [m for m in models if m not in ranked] + tail


def entry_details(board: brd.Board, model: str, g: pd.DataFrame, standing: str) -> str:
    """An entry's details: per-terrain cells, its description and standing, provenance, the command."""
    labels = [m.column_label(s) for s in SPLITS for m in mt.PAPER]
    trs = []
    for r in g.sort_values("terrain").to_dict("records"):
        cells = []
        for s in SPLITS:
            for m in mt.PAPER:
                lo, hi, _ = m.interval_keys(s, board.horizon)
                cells.append(_num(_f(r, m.metric_key(s, board.horizon)), _f(r, lo), _f(r, hi)))
        n = [
            int(_f(r, m.windows_key(s, board.horizon)))
            if np.isfinite(_f(r, m.windows_key(s, board.horizon)))
            else 0
            for s in SPLITS
            for m in mt.PAPER[:1]
        ]
        trs.append(
            f'<tr data-model="{esc(model)}" data-terrain="{esc(r["terrain"])}"><td>{esc(r["terrain"])}'
            f'</td><td>{esc(r.get("status", ""))}</td>{"".join(cells)}<td class="num">{n[0]} / {n[1]}'
            "</td></tr>"
        )
    head = "".join(f"<th>{esc(h)}</th>" for h in ("terrain", "status", *labels, "windows CV / LD"))
    facts = {
        "description": esc(_first(g, "description")),
        "standing": esc(standing),
        "link": (
            f'<a href="{esc(_href(_first(g, "link")))}">{esc(_first(g, "link"))}</a>'
            if _first(g, "link")
            else ""
        ),
        "version": esc(" ".join(x for x in (_first(g, "model_version"), _first(g, "package")) if x)),
        "code digest": f"<code>{esc(_first(g, 'code_digest')[:16])}</code>"
        if _first(g, "code_digest")
        else "",
        "predictions sha256": (
            f"<code>{esc(_first(g, 'predictions_sha256'))}</code>" if _first(g, "predictions_sha256") else ""
        ),
        "skidbench commit": f"<code>{esc(_first(g, 'git_commit')[:12])}</code>"
        if _first(g, "git_commit")
        else "",
        "split files": f"<code>{esc(_first(g, 'splits_fingerprint')[:12])}</code>",
        "runs": " ".join(f"<code>{esc(str(x)[:8])}</code>" for x in g.get("run_id", [])),
        "scored (UTC)": esc(_first(g, "start_time_utc")),
    }
    dl = (
        '<dl class="facts">'
        + "".join(
            f"<dt>{esc(k)}</dt><dd>{v}</dd>" for k, v in facts.items() if v not in (None, "", "<code></code>")
        )
        + "</dl>"
    )
    cmd = public_text(_first(g, "reproduce"))
    pre = f"<pre>{esc(cmd)}</pre>" if cmd else ""
    return (
        f'<table class="cells"><thead><tr>{head}</tr></thead><tbody>{"".join(trs)}</tbody></table>{dl}{pre}'
    )


def identity_columns(rows: pd.DataFrame) -> pd.DataFrame:
    """The submission columns (:data:`~skidbench.benchmark.board.boards.SUBMISSION_COLUMNS`) of a board's
    rows, empty where absent."""
    for k in brd.SUBMISSION_COLUMNS:
        if k not in rows:
            rows[k] = ""
    return rows
