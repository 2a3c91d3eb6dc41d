"""The text of a compare: the report's Markdown (``<out_root>/<dataset>/reports/report.md``), section by
section, and the console summary. Pure functions of what compare selected and computed
(:class:`ReportContent`) and of the few settings it reads (:class:`ReportSettings`, made by compare's
:meth:`~skidbench.benchmark.board.compare.CompareSettings.from_cfg`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import pandas as pd

from skidbench.benchmark.board.tables import SPLITS, ci_text, display_detail, markdown_table, scope_line
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring import standings as st
from skidbench.benchmark.scoring.floor import FLOOR


def sort_key(rank_by: str, horizon: float) -> str:
    """The MLflow metric the runs table is sorted by: ``rank_by``'s, or LD translational RMSRE for the
    aggregate (no one run logs the mean over terrains)."""
    return mt.rank_key("ld_trans" if rank_by == st.AGGREGATE else rank_by, horizon)


def ranked_by_line(rank_by: str, horizon: float, standings: st.Standings | None) -> str:
    if standings is None:
        what = "the four RMSREs" if rank_by == st.AGGREGATE else f"`{sort_key(rank_by, horizon)}`"
        return f"- ranked by point estimate of the mean over terrains of {what} (no paired intervals here)"
    what = f"the mean over terrains of `{standings.ranked_by}`"
    if standings.ranked_by == st.AGGREGATE:
        what = "the mean of the four RMSREs (translational and rotational, CV and LD) over terrains"
    return (f"- ranked by {what}, with its 95 % interval; best only when its paired difference from every "
            "other model is resolved, else tied; under the minimum of independent blocks not ranked "
            "(docs/intervals.md)")  # fmt: skip


def paper_claim(board: pd.DataFrame, horizon_s: float) -> list[str]:
    """The paper's claim (friction-based best on LD, comparable on CV) where no per-window tables allow
    paired intervals: not resolved by these data, with friction's place by point estimate only."""
    ok = board[board["status"] == "FINISHED"]
    if "friction" not in set(ok["model"]):
        return [
            "The friction-based model was not evaluated (or failed), so the paper's claim cannot be checked."
        ]
    lines = [
        f"**Overall: {st.UNRESOLVED}** (no per-window tables here, so no paired comparison); friction's "
        "place by point estimate only, not a ranking:",
        "",
    ]
    for metric in mt.PAPER:
        kind = metric.name
        for split in SPLITS:
            key = metric.metric_key(split, horizon_s)
            means = ok.groupby("model")[key].mean().dropna().sort_values()
            if "friction" not in means:
                continue
            rank = list(means.index).index("friction") + 1
            best, fr = means.iloc[0], means["friction"]
            lines.append(
                f"- {kind} RMSRE on {split.upper()} (mean over terrains): friction-based ranks {rank} of "
                f"{len(means)} ({fr:.2f} % vs best {means.index[0]} {best:.2f} %)"
            )
    return lines


@dataclass(frozen=True)
class ReportSettings:
    """What the report reads of the config: the dataset's name, the MLflow filter, the ranking statistic."""

    dataset: str
    filter: str | None = None
    rank_by: str = st.AGGREGATE


@dataclass(frozen=True)
class ReportContent:
    """What compare selected and computed for one report: the board of the protocol shown, its tables
    and standings, where its runs come from, the figures' Markdown and the notes."""

    tracker_uri: str
    experiment_name: str
    parent: str | None
    board: pd.DataFrame
    summary: pd.DataFrame
    detail: pd.DataFrame
    horizon: float
    protocol: str = "commanded"
    fig_md: Sequence[str] = ()
    notes: Sequence[str] = ()
    decomp_md: str = ""
    shown: Sequence[str] = ()
    links: dict[str, str] = field(default_factory=dict)
    record: dict[str, Any] = field(default_factory=dict)  # the dataset's identity (dataset.json)
    parents: Sequence[str] = ()
    left_out: Sequence[str] = ()
    standings: st.Standings | None = None


def report_md(settings: ReportSettings, c: ReportContent) -> str:
    """The report's Markdown: the header, the leaderboard, the per-terrain table, failures, left-out runs,
    the paper's claim, the protocols side by side, figures, notes and how to reproduce it."""
    parts = [*_header_lines(settings, c), *_board_lines(c), *_failed_lines(c.board), *_left_out_lines(c)]
    parts += _claim_section(c)
    if c.decomp_md:
        parts += _decomposition_lines(c)
    if c.fig_md:
        parts += ["## Figures", "", *c.fig_md]
    if c.notes:
        parts += ["## Notes", "", *[f"- {n}" for n in c.notes], ""]
    parts += _reproduce_lines(settings, c)
    return "\n".join(parts)


def _header_lines(settings: ReportSettings, c: ReportContent) -> list[str]:
    rec = c.record or {}
    runs_line = (
        f", parent run `{c.parent}`"
        if c.parent
        else f", the newest complete run of each (model, terrain) from {len(c.parents)} evaluate run(s): "
        + ", ".join(f"`{p}`" for p in c.parents)
    )
    return [
        f"# skidbench report: {settings.dataset}",
        "",
        f"Horizon {c.horizon:g} s; RMSRE of the relative translational error (position error / distance "
        "travelled) and rotational error (|yaw error| / absolute rotation), in %, lower is better. "
        "Models fitted per terrain on Train, scored on the constant-velocity (CV) and long-distance (LD) "
        "test splits.",
        *[
            f"Also `{m.short}` ({m.unit}): {m.description}, lower is better."
            for m in mt.HEADLINE
            if not m.paper
        ],
        "",
        f"- dataset: {settings.dataset} ({rec.get('source', '?')} {rec.get('root', '?')}, fingerprint "
        f"{rec.get('fingerprint', '?')})",
        f"- MLflow: `{c.tracker_uri}`, experiment `{c.experiment_name}`" + runs_line,
        f"- filter: `{settings.filter}`" if settings.filter else "- filter: none",
        *[f"- MLflow UI, {what}: <{url}>" for what, url in (c.links or {}).items()],
        ranked_by_line(settings.rank_by, c.horizon, c.standings),
        f"- input protocol: `{c.protocol}` (every model driven by the same inputs; runs of different "
        "protocols are never ranked together)",
        "",
    ]


def _board_lines(c: ReportContent) -> list[str]:
    standings = c.standings
    return [
        f"## Leaderboard, inputs={c.protocol} (mean over terrains)",
        "",
        markdown_table(c.summary),
        "",
        *([f"**{standings.verdicts['overall']}.** Each value: estimate [95 % interval] (block bootstrap, "
           "docs/intervals.md); the floor is a perfect model (the simulator's exact velocities) "
           "against this ground truth, what no model can be expected to beat.", ""]
          if standings is not None else []),
        *([scope_line(standings), ""] if standings is not None and scope_line(standings) else []),
        *differences_lines(standings),
        "## Per model and terrain",
        "",
        *([f"- {t}: {v}" for t, v in standings.verdicts.items() if t != "overall"] + [""]
          if standings is not None else []),
        markdown_table(display_detail(c.detail)),
        "",
    ]  # fmt: skip


def _failed_lines(board: pd.DataFrame) -> list[str]:
    failed = board[board["status"] != "FINISHED"]
    if not len(failed):
        return []
    return [
        "## Failed runs",
        "",
        *[
            f"- **{r.model} / {r.terrain}**: {r.status}: {r.reason or 'no reason recorded'}"
            for r in failed.itertuples()
        ],
        "",
    ]


def _left_out_lines(c: ReportContent) -> list[str]:
    if not c.left_out:
        return []
    return [
        "## Newer runs left out",
        "",
        "The board keeps the complete run named in each line.",
        "",
        *[f"- {line}" for line in c.left_out],
        "",
    ]


def _claim_section(c: ReportContent) -> list[str]:
    return [
        "## The paper's claim (friction-based best on LD, comparable on CV)",
        "",
        *(
            []
            if c.protocol == "commanded"
            else [
                f"(These runs are under inputs={c.protocol}; the paper's own check is the `commanded` one.)",
                "",
            ]
        ),
        *(_claim_lines(c.standings) if c.standings is not None else paper_claim(c.board, c.horizon)),
        "",
    ]


def _decomposition_lines(c: ReportContent) -> list[str]:
    return [
        f"## The input protocols side by side ({' / '.join(c.shown)})",
        "",
        "Per model, each RMSRE (%) under the latest evaluate of each protocol (mean over the terrains "
        "scored under all of them): commanded -> response is what the identified wheel response "
        "explains; response -> measured is what remains when the wheels' rates are known. A comparison "
        "of inputs, not a ranking.",
        "",
        c.decomp_md,
        "",
    ]


def _reproduce_lines(settings: ReportSettings, c: ReportContent) -> list[str]:
    return [
        "## Reproduce",
        "",
        "```",
        "make reproduce            # or: skidbench evaluate && skidbench compare",
        f"skidbench compare dataset={settings.dataset} inputs={c.protocol}"
        + (f" parent_run_id={c.parent}" if c.parent else ""),
        "```",
        "",
    ]


def differences_lines(standings: st.Standings | None) -> list[str]:
    """The paired differences the ranking rule decided on, from the leader (the lowest estimate) to every
    other ranked model: ``other - leader`` with its 95 % interval and whether it is resolved."""
    d = standings.differences if standings is not None else pd.DataFrame()
    ov = standings.overall.set_index("model") if standings is not None else pd.DataFrame()
    if not len(d):
        return []
    ranked = ov.loc[[m for m in ov.index if m != FLOOR and bool(ov.loc[m, "rankable"])], "estimate"]
    leader = ranked.astype(float).idxmin()
    rows = []
    for r in d[(d["a"] == leader) | (d["b"] == leader)].itertuples(index=False):
        sign, other = (-1.0, r.b) if r.a == leader else (1.0, r.a)  # differences are a - b: other - leader
        lo, hi = sorted((sign * r.lo, sign * r.hi))
        diff = ci_text(sign * r.estimate, lo, hi)
        rows.append({"model": other, "minus": leader, "difference (points)": diff,
                     "resolved": "yes" if r.resolved else "no", "_e": sign * r.estimate})  # fmt: skip
    table = pd.DataFrame(rows).sort_values("_e").drop(columns="_e")
    what = "mean of the four RMSREs" if standings.ranked_by == st.AGGREGATE else f"`{standings.ranked_by}`"
    return ["### Paired differences from the leader", "",
            f"Each model's {what} over terrains minus {leader}'s, on the same windows and the same resampled "
            "blocks, with its 95 % interval: resolved when the interval excludes 0.", "",
            markdown_table(table), ""]  # fmt: skip


def _claim_lines(standings: st.Standings) -> list[str]:
    """The claim's verdict overall (with every paired difference) and per terrain (the verdict line; with
    one terrain the overall lines are that terrain's)."""
    verdict, lines = standings.claim["overall"]
    out = [f"**Overall: {verdict}.**", "", *lines, ""]
    terrains = [scope for scope in standings.claim if scope != "overall"]
    if len(terrains) > 1:
        out += [standings.claim[t][1][0] for t in terrains]
    return out


def format_console(result: Any) -> str:
    """The console summary of a compare (a :class:`compare.CompareResult`)."""
    lines = [f"Leaderboard, inputs={result.inputs} (RMSRE %, mean over terrains; estimate [95 % interval]):",
             result.leaderboard_md, ""]  # fmt: skip
    for protocol, md in result.other_boards.items():  # each protocol's own board, never mixed
        lines += [f"Leaderboard, inputs={protocol} (its own runs, ranked on their own):", md, ""]
    if result.claim:
        lines += [f"The paper's claim (friction best on LD, comparable on CV): {result.claim}", ""]
    if result.decomposition_md:
        lines += ["Input protocols side by side (commanded / response / measured, RMSRE %):",
                  result.decomposition_md, ""]  # fmt: skip
    if result.left_out:
        lines.append(f"Left out: {len(result.left_out)} newer run(s) that are not complete (the board keeps "
                     "the complete run named):")  # fmt: skip
        lines += [f"  {line}" for line in result.left_out]
    lines.append(f"report: {result.report}")
    lines += result.written
    lines += [f"MLflow {what}: {url}" for what, url in result.links.items()]
    lines += [f"note: {n}" for n in result.notes]
    return "\n".join(lines)
