"""The README's `make reproduce` numbers and the machine-readable record they were copied from.

A `make reproduce` run writes, through `skidbench compare`, one leaderboard per input protocol with every
row's run id and provenance (``<out>/sim-mini/reports/leaderboard-<protocol>.csv``,
benchmark/board/boards.py).
:func:`record_from_reports` reduces those files to what the README shows (per protocol and model, the mean
over terrains of trans CV / trans LD / rot CV / rot LD, RMSRE % at 6 s) with where they come from (the
command, the date, the commit, the library versions, the run ids); ``python tests/readme_numbers.py <out>
[<command>]`` (``make readme-numbers OUT=<out>``) writes it to :data:`RECORD` and prints the README block
(one table per protocol, the command and date above each). ``tests/test_readme_numbers.py`` checks the
README's block against the record (every number to its printed digit) and, when asked
(``SKIDBENCH_README_MINI=1``), against a fresh `make reproduce` (physical models to the printed digit,
learned models within the spread the record states).

The block in README.md starts at the line :data:`MARKER` and ends at the next heading. Its tables are
either one protocol each (``| model | trans CV % | trans LD % | rot CV % | rot LD % |`` after a line naming
``inputs=<protocol>``) or protocols side by side (a column per protocol, its name in backticks, cells
``a / b / c / d``).
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
RECORD = REPO / "docs" / "results" / "reproduce-mini.json"
MARKER = "<!-- numbers: make reproduce; record docs/results/reproduce-mini.json -->"
DATASET = "sim-mini"
PROTOCOLS = ("commanded", "response")
COLUMNS = ("trans CV %", "trans LD %", "rot CV %", "rot LD %")
#: the spread (RMSRE points) within which a learned model's number comes back, as docs/models.md states it
#: ("read its rows as +- 0.5 point": its fit's discrete choices move with rounding-level changes)
LEARNED_SPREAD = {"gp_residual": 0.5}
PROTOCOL_TEXT = {
    "commanded": "the paper's protocol: every model driven by the commanded wheel rates",
    "response": "every model driven by the commands through the calibrated wheel response",
}


# -- the record ------------------------------------------------------------------------------------------
def _means(rows) -> dict[str, float]:
    """Per README column, the mean over the model's FINISHED terrains (compare's aggregate: the metric
    registry's ``over_terrains``)."""
    import numpy as np

    from skidbench.benchmark.scoring import metrics as mt

    ok = rows[rows["status"] == "FINISHED"]
    out = {}
    for metric in mt.PAPER:
        for split in ("cv", "ld"):
            label = metric.column_label(split)
            out[label] = float(metric.over_terrains(ok[label].to_numpy(float)))
    assert all(np.isfinite(v) for v in out.values()), f"{rows['model'].iloc[0]}: a metric is not finite"
    return {c: out[c] for c in COLUMNS}


def record_from_reports(reports: Path, command: str) -> dict[str, Any]:
    """The record of one `make reproduce`: from its ``leaderboard-<protocol>.csv`` files (compare's)."""
    import pandas as pd

    protocols: dict[str, Any] = {}
    rows_all = []
    for p in PROTOCOLS:
        board = pd.read_csv(Path(reports) / f"leaderboard-{p}.csv", dtype={"git_commit": str})
        rows_all.append(board)
        protocols[p] = {
            str(m): {
                **_means(g),
                "terrains": int((g["status"] == "FINISHED").sum()),
                "runs": list(g["run_id"]),
            }
            for m, g in board.groupby("model", sort=False)
        }
    rows = pd.concat(rows_all, ignore_index=True)
    env = sorted(c for c in rows.columns if c.startswith("env."))
    first = rows.iloc[0]
    return {
        "command": command,
        "dataset": DATASET,
        "date_utc": str(rows["start_time_utc"].max()),
        "git_commit": sorted(set(rows["git_commit"].astype(str))),
        "skidbench_version": str(first.get("skidbench_version", "")),
        "versions": {c[len("env.") :]: str(first[c]) for c in env},
        "learned_spread_points": LEARNED_SPREAD,
        "protocols": protocols,
    }


def readme_block(record: dict[str, Any]) -> str:
    """The README block of a record: :data:`MARKER`, what was run and when, one table per protocol."""
    commit = ", ".join(c[:12] for c in record["git_commit"])
    lines = [
        MARKER,
        f"`{record['command']}` (the default `mini` scale, seed 0, in a fresh output root), started "
        f"{record['date_utc']} UTC, commit {commit}: the leaderboards `compare` wrote "
        f"(`reports/leaderboard-<protocol>.csv`, every row with its run id and versions; this block and its "
        f"record `{RECORD.relative_to(REPO)}` are checked by `tests/test_readme_numbers.py`). Means over the "
        "three terrains, RMSRE % at 6 s, lower is better; learned models come back within "
        + ", ".join(f"+- {v:g} point ({m})" for m, v in record["learned_spread_points"].items())
        + ", the others to the last digit.",
    ]
    for p, models in record["protocols"].items():
        lines += ["", f"Under inputs={p} ({PROTOCOL_TEXT.get(p, p)}):", ""]
        lines += ["| model | " + " | ".join(COLUMNS) + " |", "|---|" + "---:|" * len(COLUMNS)]
        ranked = sorted(models.items(), key=lambda kv: kv[1]["trans LD %"])
        lines += [f"| {m} | " + " | ".join(f"{v[c]:.2f}" for c in COLUMNS) + " |" for m, v in ranked]
    return "\n".join(lines) + "\n"


# -- the README ------------------------------------------------------------------------------------------
def _model(cell: str) -> str:
    return cell.replace("*", "").strip().split()[0]


def parse_readme(text: str) -> dict[str, dict[str, tuple[str, ...]]]:
    """``{protocol: {model: (the four cells as printed)}}`` of the block after :data:`MARKER`.
    AssertionError when there is no marker or a table holds no protocol."""
    assert MARKER in text, f"README.md has no line {MARKER!r} above its make reproduce numbers"
    block = text.split(MARKER, 1)[1]
    block = re.split(r"\n#+ ", block, maxsplit=1)[0]
    out: dict[str, dict[str, tuple[str, ...]]] = {}
    protocol = None
    header: list[str] | None = None
    for line in block.splitlines():
        if not line.startswith("|"):
            header = None
            m = re.search(r"inputs=(\w+)", line)
            if m:
                protocol = m.group(1)
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if header is None:
            header = cells
            continue
        if set("".join(cells)) <= set("-: "):
            continue
        side_by_side = [re.search(r"`(\w+)`", h) for h in header[1:]]
        if any(side_by_side):
            for h, cell in zip(side_by_side, cells[1:], strict=True):
                if h is not None:
                    nums = re.findall(r"-?\d+\.\d+", cell)
                    out.setdefault(h.group(1), {})[_model(cells[0])] = tuple(nums)
        else:
            assert protocol is not None, f"README.md: a numbers table with no protocol above it: {line}"
            idx = [header.index(c) for c in COLUMNS]
            out.setdefault(protocol, {})[_model(cells[0])] = tuple(cells[i].replace("*", "") for i in idx)
    return out


def mismatches(readme: dict, record: dict[str, Any], tolerance: dict[str, float] | None = None) -> list[str]:
    """The README cells that do not come back from ``record``: a cell differs when the record's number
    printed to the cell's digits is another text, or, for a model in ``tolerance`` (points), when the two
    differ by more than that. Models or protocols present in one and not the other are listed too."""
    tolerance = tolerance or {}
    bad = []
    for p in sorted(set(readme) | set(record["protocols"])):
        have, want = readme.get(p, {}), record["protocols"].get(p, {})
        for m in sorted(set(have) | set(want)):
            if m not in have or m not in want:
                bad.append(f"{p}/{m}: in {'the record' if m in want else 'the README'} only")
                continue
            for col, cell in zip(COLUMNS, have[m], strict=True):
                digits = len(cell.split(".")[1]) if "." in cell else 0
                value = want[m][col]
                if m in tolerance:
                    ok = abs(float(cell) - value) <= tolerance[m]
                else:
                    ok = f"{value:.{digits}f}" == cell
                if not ok:
                    bad.append(f"{p}/{m} {col}: README {cell}, measured {value:.4f}")
    return bad


def main(argv: list[str]) -> None:
    """``python tests/readme_numbers.py <out_root> [<command>]``: write :data:`RECORD` from the run's
    leaderboard files and print the README block."""
    out = Path(argv[0])
    command = argv[1] if len(argv) > 1 else f"make reproduce OUT={out}"
    record = record_from_reports(out / DATASET / "reports", command)
    RECORD.parent.mkdir(parents=True, exist_ok=True)
    RECORD.write_text(json.dumps(record, indent=1, sort_keys=False) + "\n")
    print(f"wrote {RECORD.relative_to(REPO)}; the README block (replace the one after the marker):\n")
    print(readme_block(record))


if __name__ == "__main__":
    main(sys.argv[1:])
