"""A submission to a board: a predictions file with an identity, checked before it is scored.

``skidbench score <dataset> --predictions <file>`` (benchmark/release/score.py) scores an entry that says
who made it: the method's name (``score.name``; default the file's name), a link to its paper or code
(``score.link``, an ``http(s)://`` URL or a ``doi:``), the submitter (``score.submitter``), the date
(``score.date``, ``YYYY-MM-DD``; default today, UTC) and an optional one-line description
(``score.description``). Before anything is logged:

- the same predictions (by the file's sha256) already on the protocol's board is one entry: scored again
  under its own name, nothing changes; under another name, refused in one line naming the entry;
- a name already on the board for other predictions is refused (an entry is never replaced silently);
- physically implausible predictions are refused in one line naming the factor: the speeds (and yaw
  rates) a file predicts over the fastest commanded (the 99th percentiles of ``|(vx, vy)|`` and ``|cmd_v|``,
  of ``|wz|`` and ``|cmd_w|``, over the test sequences), against the same ratio of Train's ground truth
  (what the commands produce on this robot, at least 1); more than :data:`SPEED_FACTOR` times that is a
  unit error (km/h is 3.6 times m/s, deg/s 57.3 times rad/s) or not a prediction of this robot.
"""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from skidbench.benchmark.board.boards import SUBMISSION_COLUMNS
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.pipeline.core.errors import SkidbenchError

#: a predicted speed (or yaw rate) beyond this many times the fastest commanded is refused
SPEED_FACTOR = 2.0
#: the floors of the commanded scale (m/s, rad/s): a test set that never turns still allows a small
#: predicted yaw rate
SPEED_FLOOR, YAW_RATE_FLOOR = 0.05, 0.1
#: the unit errors a factor is told apart as (factor, what)
UNIT_ERRORS = (
    (3.6, "km/h instead of m/s"),
    (180 / np.pi, "deg/s instead of rad/s"),
    (1000.0, "mm/s instead of m/s"),
    (100.0, "cm/s instead of m/s"),
)


class SubmissionError(SkidbenchError):
    """A submission that cannot be scored (its identity, a duplicate, implausible values)."""


@dataclass(frozen=True)
class Submission:
    name: str
    link: str
    submitter: str
    date: str
    description: str = ""

    def tags(self) -> dict[str, str]:
        """The tags of its runs (:data:`~skidbench.benchmark.tracking.tags.TAG_SUBMISSION` + a field)."""
        values = {"link": self.link, "submitter": self.submitter, "submitted": self.date,
                  "description": self.description}  # fmt: skip
        return {run_tags.TAG_SUBMISSION + k: values[k] for k in SUBMISSION_COLUMNS}


def _text(key: str, value: Any) -> str:
    """A config value as the one-line text it was given (None: "")."""
    if value is None:
        return ""
    text = str(value).strip()
    if "\n" in text or "\r" in text:
        raise SubmissionError(f"score.{key}: one line, please (it holds a line break)")
    return text


def submission(
    name: str,
    link: Any,
    submitter: Any,
    date: Any = None,
    description: Any = None,
    today: dt.date | None = None,
) -> Submission:
    """The checked identity of an entry (module docstring); SubmissionError (one line) for a missing or
    malformed field."""
    link, who, desc = _text("link", link), _text("submitter", submitter), _text("description", description)
    if not link:
        raise SubmissionError(
            "score.link is not set: a submission links its paper or code (score.link=https://... or doi:...)"
        )
    if not re.fullmatch(r"(https?://[^\s/$.?#][^\s]*|doi:10\.\d{4,}/\S+)", link):
        raise SubmissionError(f"score.link={link}: not an http(s):// URL or a doi:10.xxxx/... identifier")
    if not who:
        raise SubmissionError(
            "score.submitter is not set: say who submits it (score.submitter='<name, lab>')"
        )
    if len(desc) > 300:
        raise SubmissionError(f"score.description: {len(desc)} characters; at most 300 (one line)")
    today = today or dt.datetime.now(dt.UTC).date()
    when = _text("date", date) or today.isoformat()
    try:
        day = dt.date.fromisoformat(when)
    except ValueError:
        raise SubmissionError(f"score.date={when}: not a date YYYY-MM-DD") from None
    if day > today:
        raise SubmissionError(f"score.date={when}: in the future (today is {today.isoformat()}, UTC)")
    return Submission(name, link, who, day.isoformat(), desc)


def check_entry(sub: Submission, digest: str, entries: pd.DataFrame, protocol: str) -> bool:
    """Against the protocol's entries (``model``, ``predictions_sha256``, ``submitter``, ``submitted``: one
    row per run): True when these predictions are already its entry under this name (nothing to do);
    SubmissionError when they are another entry's, or the name is another entry's."""
    if entries.empty:
        return False
    same = entries[entries["predictions_sha256"] == digest]
    if len(same):
        first = same.iloc[0]
        if str(first["model"]) == sub.name:
            return True
        raise SubmissionError(
            f"predictions sha256 {digest[:16]}... are already on the inputs={protocol} board as "
            f"{first['model']!r}{_by(first)}; the same predictions are one entry (score them as "
            f"score.name={first['model']}, or submit other predictions)"
        )
    named = entries[entries["model"].astype(str) == sub.name]
    if len(named):
        first = named.iloc[0]
        raise SubmissionError(
            f"score.name={sub.name}: already the inputs={protocol} entry of other predictions (sha256 "
            f"{str(first['predictions_sha256'])[:16]}...{_by(first)}); give this one its own name "
            f"(e.g. score.name={sub.name}_v2)"
        )
    return False


def _by(row: Mapping[str, Any]) -> str:
    who, when = str(row.get("submitter") or ""), str(row.get("submitted") or "")
    return f", submitted by {who} on {when}" if who and when else ""


def _p99(values: np.ndarray) -> float:
    values = np.asarray(values, float)
    values = values[np.isfinite(values)]
    return float(np.percentile(np.abs(values), 99)) if len(values) else 0.0


def _scales(vel: np.ndarray, cmd: pd.DataFrame) -> tuple[float, float]:
    """(speed, yaw rate) of ``vel`` (T, 3) over the commanded ones of ``cmd`` (``cmd_v``, ``cmd_w``): the
    ratios of their 99th percentiles, the commanded floored at :data:`SPEED_FLOOR` /
    :data:`YAW_RATE_FLOOR`."""
    cmd_v = max(_p99(cmd["cmd_v"].to_numpy(float)), SPEED_FLOOR)
    cmd_w = max(_p99(cmd["cmd_w"].to_numpy(float)), YAW_RATE_FLOOR)
    return _p99(np.hypot(vel[:, 0], vel[:, 1])) / cmd_v, _p99(vel[:, 2]) / cmd_w


def train_scales(train: Sequence[pd.DataFrame]) -> tuple[float, float]:
    """What the commands produce on this robot: the (speed, yaw rate) ratios of :func:`_scales` of the
    Train split's ground truth (its valid rows), each at least 1."""
    df = pd.concat([t[t["valid"].astype(bool)] for t in train], ignore_index=True) if train else None
    if df is None or not len(df):
        return 1.0, 1.0
    speed, yaw = _scales(df[["vx", "vy", "wz"]].to_numpy(float), df)
    return max(speed, 1.0), max(yaw, 1.0)


def check_plausible(
    where: str,
    predicted: Sequence[np.ndarray],
    commands: Sequence[pd.DataFrame],
    train: tuple[float, float] = (1.0, 1.0),
) -> float:
    """The predicted speeds and yaw rates over the commanded ones (:func:`_scales`, over every test
    sequence), each against what Train shows the commands produce (``train``: :func:`train_scales`);
    SubmissionError (one line, naming the factor and the unit error it looks like) when either is more than
    :data:`SPEED_FACTOR` times that. Returns the larger of the two factors."""
    vel = np.concatenate([np.asarray(v, float) for v in predicted]) if predicted else np.zeros((0, 3))
    cmd = pd.concat(list(commands), ignore_index=True)
    speed, yaw = _scales(vel, cmd)
    worst = max(
        (("speed", speed, train[0], "m/s"), ("yaw rate", yaw, train[1], "rad/s")), key=lambda x: x[1] / x[2]
    )
    what, factor, usual, unit = worst
    if factor <= SPEED_FACTOR * usual:
        return max(speed, yaw)
    near = [w for f, w in UNIT_ERRORS if abs(factor / usual / f - 1) < 0.35]
    raise SubmissionError(
        f"{where}: predicted {what} {factor:.3g} times the fastest the commands could produce (99th "
        f"percentiles; Train's ground truth: {usual:.3g} times), more than {SPEED_FACTOR:g} times that is "
        f"not this robot{': ' + near[0] + '?' if near else ''}; predict body velocities in m/s and rad/s"
    )
