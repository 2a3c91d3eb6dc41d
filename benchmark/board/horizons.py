"""Error against horizon and boards by aggressiveness (issue 49), from the per-window tables evaluate wrote.

For each protocol's board and each horizon the evaluate scored (``horizons=[...]``), the board's windows
(:func:`~skidbench.benchmark.board.boards.read_windows`) are ranked with the board's own rule
(:func:`~skidbench.benchmark.scoring.standings.build`: the paired intervals, the ranking aggregate, the
paper's claim) on every window (``all``) and on each aggressiveness stratum: the dataset's terciles of the
window's commanded acceleration (benchmark/scoring/aggressiveness.py), pooled over its terrains and test
splits at that horizon. A stratum's board says whether the paper's claim (friction best) holds there.
Under ``state`` the windows carry their aggressiveness; under the other protocols it is computed here from
the test splits' commands (the same measure). Writes ``reports/horizons.md`` and, with figures,
``reports/horizons_<protocol>.png`` (the ranking aggregate against horizon per model and stratum, with
its interval).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from skidbench.benchmark.board.boards import at_horizon, read_tables
from skidbench.benchmark.board.strata import Commands, stratum_windows
from skidbench.benchmark.board.tables import scope_line
from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.scoring import aggressiveness as ag
from skidbench.benchmark.scoring import standings as st
from skidbench.benchmark.scoring.floor import FLOOR
from skidbench.benchmark.scoring.settings import IntervalConfig
from skidbench.pipeline.core.io import atomic_path, write_text_atomic
from skidbench.pipeline.core.layout import Layout

log = logging.getLogger("skidbench.compare")
STRATA = (ag.ALL, *ag.STRATA)


def board_horizons(layout: Layout, board: pd.DataFrame, protocol: str) -> list[float]:
    """The horizons (s) of the board's per-window tables, sorted (read from the first FINISHED run's)."""
    for m, t, status in zip(board["model"], board["terrain"], board["status"], strict=True):
        if status != "FINISHED":
            continue
        stem = layout.eval_stem(str(m), str(t), protocol)
        try:
            w = pd.read_parquet(stem.with_name(stem.name + ".windows.parquet"), columns=["horizon_s"])
        except (OSError, ValueError, KeyError):
            continue
        return sorted({float(h) for h in w["horizon_s"]})
    return []


#: the columns of the per-window tables the strata and their boards read
COLUMNS = ("horizon_s", "aggressiveness", *st.WINDOW_COLUMNS)


def strata_standings(
    layout: Layout, board: pd.DataFrame, protocol: str, horizon_s: float, intervals: IntervalConfig,
    rank_by: str, half_track: float, commands: Commands | None = None,
) -> dict[str, st.Standings]:  # fmt: skip
    """``{stratum: Standings}`` of one board at one horizon (``all`` and the terciles, module docstring):
    each the overall ranking and claim only (``st.build(..., detail=False)``: what the report shows).
    ``commands``: the test splits' commands read so far
    (:func:`~skidbench.benchmark.board.strata.add_aggressiveness`)."""
    windows = at_horizon(read_tables(layout, board, protocol, COLUMNS)[0], horizon_s)
    if not any(m != FLOOR for m, _ in windows):
        return {}
    strata = stratum_windows(layout, windows, horizon_s, half_track, commands)
    return {name: st.build(part, horizon_s, intervals, rank_by, detail=False)
            for name, part in strata.items()}  # fmt: skip


def _cell(row: pd.Series) -> str:
    est = row.get("estimate")
    if est is None or not np.isfinite(float(est)):
        return "-"
    lo, hi = row.get("lo"), row.get("hi")
    text = f"{float(est):.2f}"
    if lo is not None and np.isfinite(float(lo)):
        text += f" [{float(lo):.2f}, {float(hi):.2f}]"
    rank = str(row.get("rank") or "")
    return text + (f" #{rank}" if rank else "")


def report_markdown(results: Mapping[str, Mapping[float, Mapping[str, st.Standings]]]) -> str:
    """The markdown of :func:`horizon_report`'s results: per protocol a table per stratum (models x
    horizons: the ranking aggregate [interval] #rank) and the paper's claim per stratum and horizon."""
    lines = ["# Error against horizon, by aggressiveness", "",
             "The ranking aggregate (the mean of translational and rotational RMSRE on CV and LD, %) with "
             "its 95 % interval and rank (ties share a rank), per horizon, on every window and on each "
             "tercile of the windows' commanded acceleration (benchmark/scoring/aggressiveness.py). "
             "Protocols are never ranked together.", ""]  # fmt: skip
    for protocol, by_h in results.items():
        horizons = sorted(by_h)
        lines += [f"## inputs={protocol}", ""]
        for stratum in STRATA:
            models: list[str] = []
            for h in horizons:
                s = by_h[h].get(stratum)
                if s is not None:
                    models += [m for m in s.overall["model"] if m not in models]
            if not models:
                continue
            head = "| model | " + " | ".join(f"{h:g} s" for h in horizons) + " |"
            lines += [f"### {stratum} windows", "", head, "|---|" + "---|" * len(horizons)]
            for m in models:
                cells = []
                for h in horizons:
                    s = by_h[h].get(stratum)
                    hit = s.overall[s.overall["model"] == m] if s is not None else pd.DataFrame()
                    cells.append(_cell(hit.iloc[0]) if len(hit) else "-")
                lines.append(f"| {m} | " + " | ".join(cells) + " |")
            claims = [
                f"{h:g} s: {by_h[h][stratum].claim['overall'][0]}" for h in horizons if stratum in by_h[h]
            ]
            lines += ["", f"Friction best ({stratum} windows): " + "; ".join(claims) + ".", ""]
            scope = next((scope_line(by_h[h][stratum]) for h in horizons if stratum in by_h[h]), "")
            lines += [scope, ""] if scope else []
    return "\n".join(lines) + "\n"


def horizon_figure(
    by_h: Mapping[float, Mapping[str, st.Standings]], title: str, path: Path, dpi: int
) -> Path:
    """The ranking aggregate against horizon, one line per model with its interval, a panel per stratum."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    horizons = sorted(by_h)
    fig, axes = plt.subplots(1, len(STRATA), figsize=(4.0 * len(STRATA), 3.6), sharey=True)
    for ax, stratum in zip(axes, STRATA, strict=True):
        models: list[str] = []
        for h in horizons:
            if stratum in by_h[h]:
                models += [m for m in by_h[h][stratum].overall["model"] if m not in models and m != FLOOR]
        for m in models:
            est, lo, hi = [], [], []
            for h in horizons:
                s = by_h[h].get(stratum)
                hit = s.overall[s.overall["model"] == m] if s is not None else pd.DataFrame()
                row = hit.iloc[0] if len(hit) else {}
                est.append(float(row.get("estimate", np.nan)))
                lo.append(float(row.get("lo", np.nan)))
                hi.append(float(row.get("hi", np.nan)))
            e = np.asarray(est)
            yerr = np.vstack([e - np.asarray(lo), np.asarray(hi) - e])
            ax.errorbar(horizons, e, yerr=np.where(np.isfinite(yerr), np.abs(yerr), 0.0), marker="o",
                        capsize=2, label=m)  # fmt: skip
        ax.set_title(f"{stratum} windows")
        ax.set_xlabel("horizon (s)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(st.AGGREGATE_LABEL)
    axes[-1].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)
    return path


def horizon_report(
    layout: Layout, boards: Mapping[str, pd.DataFrame], intervals: IntervalConfig, rank_by: str,
    half_track: float, out: Path, figures_dpi: int | None,
) -> list[Path]:  # fmt: skip
    """Writes ``horizons.md`` (and a figure per protocol when ``figures_dpi``) in ``out`` for the boards
    ``{protocol: board rows}`` whose evaluates scored more than one horizon; returns the files written."""
    todo = {p: board_horizons(layout, b, p) for p, b in boards.items()}
    results: dict[str, dict[float, dict[str, st.Standings]]] = {
        p: {} for p, hs in todo.items() if len(hs) > 1
    }
    # horizon by horizon, every protocol's boards in turn: they resample the same strata (the same bootstrap
    # draws, kept while they are recent); the test splits' commands are read once for every horizon
    commands: dict[str, Commands] = {p: {} for p in results}
    for h in sorted({h for p in results for h in todo[p]}):
        for protocol in [p for p in results if h in todo[p]]:
            try:  # the strata of a protocol other than state are read from the test splits' commands
                results[protocol][h] = strata_standings(layout, boards[protocol], protocol, h, intervals,
                                                        rank_by, half_track, commands[protocol])  # fmt: skip
            except EvaluationError as exc:  # the splits are gone: the boards stand, this report cannot
                log.warning("compare: no error against horizon for inputs=%s: %s", protocol, exc)
                del results[protocol]
    results = {p: dict(sorted(by_h.items())) for p, by_h in results.items()}
    if not results:
        return []
    files = [out / "horizons.md"]
    write_text_atomic(files[0], report_markdown(results))
    if figures_dpi:
        for protocol, by_h in results.items():
            files.append(horizon_figure(by_h, f"error against horizon (inputs={protocol})",
                                        out / f"horizons_{protocol}.png", figures_dpi))  # fmt: skip
    return files
