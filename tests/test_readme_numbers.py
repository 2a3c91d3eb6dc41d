"""The README's `make reproduce` numbers are a run's numbers (tests/readme_numbers.py): the block after
the README's marker equals, to every printed digit, the record `make readme-numbers` wrote from that run's
leaderboard files (docs/results/reproduce-mini.json); the record is a complete `make reproduce` (every
model of both protocols on every terrain, one commit); the tool chain (compare's leaderboard files ->
record -> README block -> parsed back) round-trips on the session's tiny quick start; and, when asked with
``SKIDBENCH_README_MINI=1`` (a `make reproduce` on `mini`: minutes of CPU), a fresh run prints the README's
numbers: physical models to the printed digit, learned models within their stated spread."""

from __future__ import annotations

import json
import os
import subprocess

import pytest
from readme_numbers import (
    COLUMNS,
    LEARNED_SPREAD,
    MARKER,
    PROTOCOLS,
    RECORD,
    REPO,
    mismatches,
    parse_readme,
    readme_block,
    record_from_reports,
)

MODELS = {"ideal", "edd", "full_linear", "roc", "enhanced", "friction", "drive_blr", "gp_residual"}
README = REPO / "README.md"


def test_the_readme_numbers_are_those_of_the_committed_record():
    record = json.loads(RECORD.read_text())
    readme = parse_readme(README.read_text())
    assert mismatches(readme, record) == []
    text = README.read_text().split(MARKER, 1)[1]
    assert record["command"].split(" OUT=")[0] in text and record["date_utc"] in text


def test_the_record_is_one_complete_make_reproduce():
    record = json.loads(RECORD.read_text())
    assert record["command"].startswith("make reproduce") and record["dataset"] == "sim-mini"
    assert set(record["protocols"]) == set(PROTOCOLS)
    for p, models in record["protocols"].items():
        assert set(models) == MODELS, p
        assert all(m["terrains"] == 3 and len(m["runs"]) == 3 for m in models.values()), p
    assert len(record["git_commit"]) == 1 and not record["git_commit"][0].endswith("+dirty")


def test_the_side_by_side_form_is_read_and_a_changed_digit_is_caught():
    text = "\n".join([
        MARKER, "", "| model | `commanded` | `response` |", "|---|---|---|",
        "| friction | **6.91 / 3.85 / 7.85 / 5.72** | **5.40 / 2.23 / 5.88 / 3.12** |",
        "| gp_residual (learned) | 10.20 / 4.53 / 8.74 / 5.58 | 9.67 / 4.11 / 6.23 / 5.08 |", "", "## Next",
        "| other | 1.00 |",
    ])  # fmt: skip
    readme = parse_readme(text)
    assert readme["commanded"]["friction"] == ("6.91", "3.85", "7.85", "5.72")
    assert readme["response"]["gp_residual"] == ("9.67", "4.11", "6.23", "5.08")
    values = lambda cells, d=0.0: {c: float(v) + d for c, v in zip(COLUMNS, cells, strict=True)}  # noqa: E731
    record = {"protocols": {p: {m: values(v) for m, v in ms.items()} for p, ms in readme.items()}}
    assert mismatches(readme, record, LEARNED_SPREAD) == []
    record["protocols"]["commanded"]["friction"]["rot LD %"] = 5.726  # prints 5.73
    record["protocols"]["response"]["gp_residual"] = values(readme["response"]["gp_residual"], 0.4)
    assert mismatches(readme, record, LEARNED_SPREAD) == [
        "commanded/friction rot LD %: README 5.72, measured 5.7260"
    ]


@pytest.mark.slow  # the session's quick start (built once, shared with test_e2e)
def test_the_record_of_a_make_reproduce_round_trips_through_the_readme_block(readme_reproduce):
    """On the quick start's tiny `make reproduce`: its leaderboard files -> a record -> the README block
    -> parsed back: every number as printed; one physical number off by 0.01 is caught."""
    reports = readme_reproduce["root"] / "sim-tiny" / "reports"
    record = record_from_reports(reports, "make reproduce SCALE=tiny OUT=<tmp>")
    assert set(record["protocols"]) == set(PROTOCOLS)
    assert all(set(ms) == MODELS for ms in record["protocols"].values())
    assert record["versions"]["numpy"] and record["date_utc"]
    block = readme_block(record)
    readme = parse_readme(f"# x\n\n{block}\n## After\n")
    assert mismatches(readme, record) == []
    record["protocols"]["commanded"]["friction"]["trans LD %"] += 0.01
    (bad,) = mismatches(readme, record)
    assert bad.startswith("commanded/friction trans LD %: README ")


@pytest.mark.slow
@pytest.mark.skipif(
    os.environ.get("SKIDBENCH_README_MINI") != "1",
    reason="a `make reproduce` on mini (minutes of CPU): set SKIDBENCH_README_MINI=1 to run it",
)
def test_a_fresh_make_reproduce_prints_the_readme_numbers(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run(["make", "reproduce", f"OUT={out}"], cwd=REPO, capture_output=True, text=True,
                          timeout=3 * 3600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    fresh = record_from_reports(out / "sim-mini" / "reports", f"make reproduce OUT={out}")
    assert mismatches(parse_readme(README.read_text()), fresh, LEARNED_SPREAD) == []
