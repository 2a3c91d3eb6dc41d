"""``python -m perf.snapshot <out_root> <dataset> <name> [--made-by "<command>"]``: the boards of an
output root as a generated results page, ``perf/results/board_<name>.md``.

It copies what ``skidbench compare`` wrote into ``<out_root>/<dataset>/reports/``: from ``report.md`` the
boards (the leaderboard with its intervals, ranks, standing and floor, the paired differences the ranking
rule decided on, every model and terrain, the paper's claim, the protocols side by side) and its notes,
without the figures; the mean-over-terrains board of every other protocol (``leaderboard-<inputs>.md``);
and ``horizons.md`` (error against horizon, ``inputs=state``) when compare wrote one. The header names the
output root's dataset identity and the commits and start times of the runs behind the boards (the
leaderboard CSVs), so the page says what made its numbers; ``--made-by`` adds the command that made the
output root (``make reproduce``, ...). The docs link these pages instead of quoting their numbers.
"""

from __future__ import annotations

import argparse
import csv
import re
import shlex
import sys
from pathlib import Path

from .pages import RESULTS, dataset_identity, publish

#: report.md's sections that are figures or how to rerun it: not copied
SKIP = ("## Figures", "## Reproduce")


def _sections(text: str) -> str:
    """``report.md`` from its first board to its end, without the skipped sections and image lines."""
    out, keep = [], False
    for line in text.splitlines():
        if line.startswith("## "):
            keep = not line.startswith(SKIP)
        if keep and not line.startswith("!["):
            out.append(line)
    return "\n".join(out)


def _other_boards(reports: Path, report: str) -> str:
    """The mean-over-terrains board of each protocol report.md does not show (``leaderboard-<inputs>.md``:
    its first table and the verdict lines under it)."""
    out = []
    for path in sorted(reports.glob("leaderboard-*.md")):
        inputs = path.stem.removeprefix("leaderboard-")
        if re.search(r"-\d{8}T\d{6}Z$", inputs) or f"## Leaderboard, inputs={inputs} " in report:
            continue
        lines = path.read_text().splitlines()
        first = next((i for i, line in enumerate(lines) if line.startswith("|")), len(lines))
        end = next(
            (i for i in range(first, len(lines)) if lines[i].startswith("| model | inputs")), len(lines)
        )
        out += [f"## Leaderboard, inputs={inputs} (mean over terrains)", "", *lines[first:end]]
    return "\n".join(out).rstrip()


def _runs(reports: Path) -> str:
    """The commits and the start times of the runs on the leaderboards (their CSVs)."""
    commits, times = set(), []
    for path in sorted(reports.glob("leaderboard-*.csv")):
        if re.search(r"-\d{8}T\d{6}Z\.csv$", path.name):  # the time-stamped copies
            continue
        with path.open(newline="") as fh:
            for row in csv.DictReader(fh):
                commits.add(row.get("git_commit", "") or "?")
                times.append(row.get("start_time_utc", ""))
    times = sorted(t for t in times if t)
    when = f", started {times[0]} to {times[-1]}" if times else ""
    return f"Runs at commit {', '.join(sorted(commits)) or '?'}{when}."


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(prog="python -m perf.snapshot", description=__doc__.split("\n\n")[0])
    ap.add_argument("out_root", type=Path)
    ap.add_argument("dataset")
    ap.add_argument("name", help="the page: perf/results/board_<name>.md")
    ap.add_argument("--made-by", default="", help="the command(s) that made the output root")
    ap.add_argument("--results", type=Path, default=RESULTS, help="the folder of the page (perf/results)")
    a = ap.parse_args(argv)
    root = a.out_root / a.dataset
    reports = root / "reports"
    report = reports / "report.md"
    if not report.is_file():
        raise SystemExit(f"{report}: no report (run skidbench compare on this output root first)")
    text = report.read_text()
    body = "\n\n".join(filter(None, [_sections(text), _other_boards(reports, text)]))
    if (reports / "horizons.md").is_file():
        body += "\n\n" + (reports / "horizons.md").read_text()
    made = f" The output root was made by `{a.made_by}`." if a.made_by else ""
    about = f"Dataset {dataset_identity(root)}.{made} {_runs(reports)}"
    command = "python -m perf.snapshot " + shlex.join(sys.argv[1:] if argv is None else argv)
    path = publish(f"board_{a.name}", command, about, body, a.results)
    print(path)
    return path


if __name__ == "__main__":
    main()
