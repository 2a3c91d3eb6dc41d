"""``python -m perf.snapshot <out_root> <dataset> <name> [--made-by "<command>"]``: the boards of an
output root as a generated results page, ``perf/results/board_<name>.md``.

It copies what ``skidbench compare`` wrote into ``<out_root>/<dataset>/reports/``: from ``report.md`` the
boards (the leaderboard with its intervals, ranks, standing and floor, the paired differences the ranking
rule decided on, every model and terrain, the paper's claim, the protocols side by side) and its notes,
without the figures; the mean-over-terrains board of every other protocol (``leaderboard-<inputs>.md``);
the ground truth's loop closure (``groundtruth/loop_closure.json``); what ``calibrate`` identified per
terrain (``calibration/<terrain>.json``); and ``horizons.md`` (error
against horizon, ``inputs=state``) when compare wrote one. The header names the output root's dataset
identity and the commits and start times of the runs behind the boards (the leaderboard CSVs), so the
page says what made its numbers; ``--made-by`` adds the command that made the output root (``make
reproduce``, ...). The docs link these pages instead of quoting their numbers.
"""

from __future__ import annotations

import argparse
import csv
import json
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


def _constant(c: dict, spec: float | None) -> str:
    if not c or not c.get("identified"):
        return f"{spec} (spec sheet; not identified)"
    lo, hi = c.get("ci", [float("nan")] * 2)
    return (
        f"{spec} -> {c['value']:.4g} [{lo:.4g}, {hi:.4g}] ({c.get('ratio_to_spec', float('nan')):.3f}, "
        f"{c.get('n_rows', '?')} rows)"
    )


def _calibrations(root: Path) -> str:
    """What ``calibrate`` identified per terrain (``calibration/<terrain>.json``): the effective wheel radius
    and track width against the spec sheet with their 95 % intervals, and the wheel response chosen."""
    rows = []
    for path in sorted((root / "calibration").glob("*.json")):
        try:
            cal = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if "wheel_radius" not in cal:
            continue
        spec, wr = cal.get("spec", {}), cal.get("wheel_response") or {}
        resp = "not identified"
        if wr.get("identified"):
            resp = (
                f"{wr.get('structure')}: {wr.get('rmse_command', float('nan')):.3f} -> "
                f"{wr.get('rmse_response', float('nan')):.3f} ({wr.get('heldout_rmse', float('nan')):.3f})"
            )
        radius = _constant(cal["wheel_radius"], spec.get("wheel_radius"))
        track = _constant(cal.get("track_width", {}), spec.get("track_width"))
        rows.append(f"| {cal.get('terrain', path.stem)} | {radius} | {track} | {resp} |")
    if not rows:
        return ""
    head = [
        "## Calibration (`skidbench calibrate`, each terrain's Train)",
        "",
        "| terrain | wheel radius (m): spec -> calibrated [95 % interval] (ratio, rows) | track width (m): "
        "the same | wheel response: structure: encoder RMSE (rad/s) commands -> response (held out) |",
        "|---|---|---|---|",
    ]
    return "\n".join(head + rows)


def _ground_truth(root: Path) -> str:
    """The ground truth's loop closure over the loop trials and, on simulated data, its error against the
    simulator's truth (``groundtruth/loop_closure.json``)."""
    try:
        lc = json.loads((root / "groundtruth" / "loop_closure.json").read_text())
    except (OSError, json.JSONDecodeError):
        return ""
    if not lc.get("trials"):
        return ""
    pct = lambda k: 100 * float(lc.get(k, float("nan")))  # noqa: E731
    lines = [
        "## Ground truth (`groundtruth/loop_closure.json`)",
        "",
        f"Method `{lc.get('method')}`, {lc['trials']} loop trials: loop-closure error translational "
        f"{pct('translational_mean'):.2f} % +- {pct('translational_std'):.2f} %, rotational "
        f"{pct('rotational_mean'):.2f} % +- {pct('rotational_std'):.2f} % (flagged: {lc.get('flagged')}).",
    ]
    te = lc.get("truth_error") or {}
    if te:
        ate, rpe = 100 * te.get("ate_rms_m", float("nan")), 100 * te.get("rpe_trans_rel_rms", float("nan"))
        lines.append(
            f"Against the simulator's truth: absolute error {ate:.1f} cm RMS, "
            f"6 s relative translational error {rpe:.2f} % RMS."
        )
    return "\n".join(lines)


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
    body = "\n\n".join(
        filter(
            None, [_sections(text), _other_boards(reports, text), _ground_truth(root), _calibrations(root)]
        )
    )
    if (reports / "horizons.md").is_file():
        body += "\n\n" + (reports / "horizons.md").read_text()
    made = f" The output root was made by `{a.made_by}`." if a.made_by else ""
    about = f"Dataset {dataset_identity(root)}.{made} {_runs(reports)}"
    args = sys.argv[1:] if argv is None else list(argv)
    # the page is committed: the output root is `<out>`, never this machine's path
    command = "python -m perf.snapshot " + shlex.join(args)
    command, about = (t.replace(str(a.out_root.resolve()), "<out>").replace(str(a.out_root), "<out>")
                      for t in (command, about))  # fmt: skip
    path = publish(f"board_{a.name}", command, about, body, a.results)
    print(path)
    return path


if __name__ == "__main__":
    main()
