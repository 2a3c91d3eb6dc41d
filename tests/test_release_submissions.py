"""A submission's identity and plausibility (benchmark/release/submission.py), and the command line's
strings (pipeline/cli/main.py ``as_string``): fast checks without a dataset. tests/test_release.py runs
them through the CLI on the quick start's dataset."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pandas as pd
import pytest

from skidbench.benchmark.release import submission as sb
from skidbench.pipeline.cli.main import as_string
from skidbench.pipeline.cli.overrides import check_overrides

TODAY = dt.date(2026, 11, 28)


def test_a_submission_carries_a_link_a_submitter_and_a_date():
    s = sb.submission("mine", "https://example.org/m", "Lab B", None, "fast", today=TODAY)
    assert (s.link, s.submitter, s.date, s.description) == (
        "https://example.org/m",
        "Lab B",
        "2026-11-28",
        "fast",
    )
    assert (
        sb.submission("mine", "doi:10.1109/ICRA.2019.1", "B", "2026-01-02", today=TODAY).date == "2026-01-02"
    )
    assert s.tags()["skidbench.submission.submitter"] == "Lab B"
    for args, message in [
        ((None, "B"), "score.link is not set"),
        (("example.org", "B"), r"not an http\(s\):// URL"),
        (("https://x.org", ""), "score.submitter is not set"),
        (("https://x.org", "B", "28/11/2026"), "not a date YYYY-MM-DD"),
        (("https://x.org", "B", "2026-12-01"), "in the future"),
    ]:
        with pytest.raises(sb.SubmissionError, match=message):
            sb.submission("mine", *args, today=TODAY)


def test_the_same_predictions_are_one_entry_and_a_name_is_never_replaced():
    entries = pd.DataFrame({"model": ["a", "a"], "predictions_sha256": ["d1", "d1"], "submitter": ["X", "X"],
                            "submitted": ["2026-11-01"] * 2})  # fmt: skip
    a = sb.submission("a", "https://x.org", "X", today=TODAY)
    b = sb.submission("b", "https://x.org", "Y", today=TODAY)
    assert sb.check_entry(a, "d1", entries, "commanded") is True  # already this entry: nothing to do
    assert sb.check_entry(b, "d2", entries, "commanded") is False  # a new entry
    with pytest.raises(
        sb.SubmissionError, match="already on the inputs=commanded board as 'a', submitted by X"
    ):
        sb.check_entry(b, "d1", entries, "commanded")
    with pytest.raises(sb.SubmissionError, match="score.name=a: already the inputs=commanded entry of other"):
        sb.check_entry(a, "d2", entries, "commanded")


def test_predictions_in_kmh_or_degrees_are_refused_naming_the_factor():
    rng = np.random.default_rng(0)
    cmd = pd.DataFrame({"cmd_v": rng.uniform(-1, 1, 500), "cmd_w": rng.uniform(-2, 2, 500)})
    vel = np.c_[cmd["cmd_v"] * 0.9, np.zeros(500), cmd["cmd_w"] * 0.7]  # what a skid-steer robot does
    assert sb.check_plausible("p.csv", [vel], [cmd]) == pytest.approx(0.9, rel=0.02)
    with pytest.raises(sb.SubmissionError, match=r"predicted speed 3\.2\d times .*: km/h instead of m/s\?"):
        sb.check_plausible("p.csv", [vel * [3.6, 1, 1]], [cmd])
    with pytest.raises(
        sb.SubmissionError, match=r"predicted yaw rate 40\.\d times .*deg/s instead of rad/s\?"
    ):
        sb.check_plausible("p.csv", [vel * [1, 1, 180 / np.pi]], [cmd])
    # a robot whose Train truth outruns its commands (a scaled command): twice that is still allowed
    assert sb.check_plausible("p.csv", [vel * [2.5, 1, 1]], [cmd], (1.5, 1.0)) == pytest.approx(
        2.25, rel=0.02
    )


def test_a_string_setting_keeps_the_text_it_was_given():
    assert as_string("score.name=nan") == "score.name='nan'"
    assert as_string("score.date=2026") == "score.date='2026'"
    assert as_string("score.description=fast, small") == "score.description='fast, small'"
    assert as_string("score.description=it's, fast") == "score.description='it\\'s, fast'"
    assert (
        as_string("score.name=abc") == "score.name=abc" and as_string("score.name=null") == "score.name=null"
    )
    assert as_string("horizons=[6]") == "horizons=[6]" and as_string("dataset=a,b", True) == "dataset=a,b"
    _, cfg = check_overrides("score", [as_string("score.name=nan"), "score.predictions=p.csv", "dataset=x"])
    assert cfg.score.name == "nan"
