"""``skidbench score <dataset> --predictions <file>``: a model from anywhere, scored from a file.

The contract is a file, not a Python class. A model (C++, PyTorch, MATLAB, ...) is run on the input
tables ``skidbench export`` writes for a protocol (``inputs/<protocol>/<terrain>/<cv|ld>/<seq>.parquet``:
pipeline/core/protocol.py ``model_inputs``, inputs only) and writes ONE Parquet or CSV file with a row per
input row of every CV and LD sequence:

    sequence, t, vx, vy, wz            body velocities (m/s, m/s, rad/s) at the row's time t (s)
    [cov_vx_vx, cov_vx_vy, cov_vx_wz, cov_vy_vy, cov_vy_wz, cov_wz_wz]   optional: the predictive
                                        covariance of (vx, vy, wz), all six or none

The file is checked against the dataset's splits before anything is logged (benchmark/release/
predictions_file.py), each problem one line naming the file and the sequence. Rows may come in any order
(they are sorted by time within a sequence).

A submission has an identity and must be plausible (benchmark/release/submission.py: a link, a
submitter, a date; one entry per predictions digest; speeds the commands could produce). Then every window
is scored by the same machinery as ``evaluate`` (benchmark/scoring/predictions.py
``score_split``/``score_cells``: the same horizons, minimum distance and rotation, read from the latest
evaluate of the protocol in the results table, else from the imported bundle, else evaluate's defaults),
written to the dataset's results table (``<ds>/results/score-<sha256[:12]>-<UTC stamp>.parquet``, one row
per cell, ``external`` true: benchmark/board/results.py) and logged to MLflow from those rows as one child
run per terrain of that evaluate (``skidbench.external=true``, the file's sha256 in
``skidbench.predictions_sha256``, model version ``external``, the identity in ``skidbench.submission.*``),
so ``compare`` ranks it on the same board.

Scoring needs the CV/LD ground truth: a dataset imported from the public half of a bundle has none
(pipeline/datasets/imported.py refuses ``score`` there). ``score.check=true`` (:func:`check_predictions`)
checks a file's shape and plausibility against the test sequences' clocks and commands, read from the
split files or, without them, from the public half's model-input tables: what a lab runs before it
submits.
"""

from __future__ import annotations

import datetime as dt
import logging
import re
import shlex
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa

from skidbench.benchmark.board import boards as brd
from skidbench.benchmark.board import results as rt
from skidbench.benchmark.board.selection import results_of
from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.evaluate.testsets import (
    TRAIN,
    check_horizons,
    find_terrains,
    load_test_split,
    split_files,
    split_fingerprint,
)
from skidbench.benchmark.release import submission as sb
from skidbench.benchmark.release.predictions_file import PredictionsError, align, read_predictions
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring.horizon import HorizonConfig
from skidbench.benchmark.scoring.predictions import Score, TestSequence, score_cells, score_split
from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.pipeline.core.errors import one_line
from skidbench.pipeline.core.io import sha256_file, write_parquet_atomic
from skidbench.pipeline.core.layout import Layout
from skidbench.pipeline.core.protocol import check_protocol
from skidbench.pipeline.runner import environment

log = logging.getLogger(__name__)

EXTERNAL_VERSION = "external"


# -- the settings every row of the board is scored with -----------------------------------------------
def evaluate_defaults() -> dict[str, Any]:
    """``splits``, ``horizons``, ``min_distance_m``, ``min_rotation_deg`` of evaluate's defaults (its root
    keys' dataclass, :class:`~skidbench.benchmark.evaluate.settings.EvaluateOptions`)."""
    from skidbench.benchmark.evaluate.settings import EvaluateOptions

    d = EvaluateOptions()
    return {"splits": list(d.splits), "horizons": list(d.horizons), "min_distance_m": d.min_distance_m,
            "min_rotation_deg": d.min_rotation_deg}  # fmt: skip


def board_settings(table: pd.DataFrame, protocol: str, root: Path) -> tuple[dict[str, Any], str | None, str]:
    """The settings to score with, the parent run to hang the rows from (None: start one) and where
    the settings come from: the latest evaluate of ``protocol`` in the dataset's results ``table``, else
    the imported bundle's board, else evaluate's defaults."""
    settings = evaluate_defaults()
    parent = rt.latest_evaluate(table, protocol)
    if parent is not None:
        got = rt.settings_of(table, parent)
        settings.update({k: v for k, v in got.items() if k in settings})
        return settings, parent, f"the latest evaluate under inputs={protocol} (run {parent})"
    from skidbench.benchmark.release.bundle import read_bundle_doc

    doc = read_bundle_doc(Path(root) / "bundle")
    if doc:
        metric = doc.get("metric") or {}
        settings.update({k: metric[k] for k in settings if metric.get(k) is not None})
        return settings, None, "the imported bundle's board"
    return settings, None, "evaluate's defaults (no evaluate run yet)"


# -- scoring and logging ------------------------------------------------------------------------------
@dataclass
class ScoreResult:
    name: str
    protocol: str
    sha256: str
    parent_run_id: str
    rows: list[dict[str, Any]] = field(default_factory=list)  # per terrain: run_id and metrics
    settings_from: str = ""
    horizon: float = 6.0  # the first horizon scored (the board's)
    submission: sb.Submission | None = None
    already: bool = False  # the same predictions were this entry already: nothing logged


def default_name(path: Path) -> str:
    stem = Path(path).name.split(".")[0]
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", stem).strip("_") or "external"


def check_name(name: str) -> str:
    """``name`` for the board; PredictionsError when it is an installed model's (whose row it would
    replace) or not a plain name."""
    from skidbench.benchmark.evaluate.fit_record import installed_models

    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", name):
        raise PredictionsError(f"score.name={name!r}: use letters, digits, '_', '.', '-'")
    if name in installed_models():
        raise PredictionsError(
            f"score.name={name}: the name of an installed model, whose row it would replace on the board; "
            "give "
            f"the external row its own name (e.g. score.name={name}_external)"
        )
    return name


def _tests(
    layout: Layout, splits: list[str], horizons: list[float] | None, hcfg: HorizonConfig | None = None
) -> tuple[dict, dict]:
    """Per terrain and test split the test sequences (their split files: the truth), and per terrain the
    files evaluate fingerprints (its child runs' tag: compare matches the rows by it)."""
    tests: dict[str, dict[str, list[TestSequence]]] = {}
    files_of: dict[str, list[Path]] = {}
    for terrain in find_terrains(layout):
        tests[terrain] = {}
        files: list[Path] = []
        for split in splits:
            seqs = load_test_split(layout, terrain, split)
            if horizons is not None:
                check_horizons(terrain, split, seqs, horizons, hcfg)
            tests[terrain][split] = [s for s in seqs if len(s.table)]  # an empty sequence: no row to predict
            files.extend(s.path for s in seqs)
        files_of[terrain] = split_files(layout, terrain, TRAIN) + files
    return tests, files_of


def entries(table: pd.DataFrame, protocol: str) -> pd.DataFrame:
    """The protocol's external entries on the board of the results ``table``: ``model``,
    ``predictions_sha256``, ``submitter``, ``submitted`` (one row per run; empty without a board)."""
    cols = ["model", "predictions_sha256", "submitter", "submitted"]
    board = brd.protocol_board(table, protocol)
    if board is None or "external" not in board.rows:
        return pd.DataFrame(columns=cols)
    rows = board.rows[board.rows["external"].astype(bool)]
    return pd.DataFrame({c: rows[c] if c in rows else "" for c in cols})


def score_predictions(
    layout: Layout,
    tracker: trk.Tracker,
    path: Path,
    entry: sb.Submission,
    protocol: str = "commanded",
) -> ScoreResult:
    """Checks the predictions file against the splits and the board, scores every window and logs one
    external child run per terrain with the entry's identity (module docstring). Nothing is logged when
    the file fails a check or is already this entry."""
    path = Path(path).expanduser().absolute()
    protocol = check_protocol(protocol)
    check_name(entry.name)
    table = results_of(layout, tracker.dataset_id, tracker.experiment_name)
    settings, parent, source = board_settings(table, protocol, layout.root)
    splits = [str(s) for s in settings["splits"]]
    horizons = [float(h) for h in settings["horizons"]]
    hcfg = HorizonConfig(
        horizons[0], float(settings["min_distance_m"]), float(np.deg2rad(float(settings["min_rotation_deg"])))
    )
    # 1. the splits, the file and the board, checked before anything is logged
    tests, files_of = _tests(layout, splits, horizons, hcfg)
    preds = read_predictions(path)
    aligned = align(path, preds, tests)
    plausible(layout, path, aligned, tests)
    digest = sha256_file(path)
    if sb.check_entry(entry, digest, entries(table, protocol), protocol):
        return ScoreResult(entry.name, protocol, digest, parent or "", [], source, horizons[0], entry, True)
    # 2. every window scored (the same functions as evaluate), then logged
    scored = {}
    for terrain in tests:
        scores: list[Score] = []
        frames = []
        for split in splits:
            vels, covs = aligned[terrain][split]
            w = score_split(tests[terrain][split], vels, horizons, hcfg, covs, None)
            if len(w):
                w.insert(0, "split", split)
                frames.append(w)
            scores += score_cells(w, split, horizons)
        scored[terrain] = (scores, pd.concat(frames, ignore_index=True) if frames else pd.DataFrame())
    res = _log(layout, tracker, path, entry, protocol, digest, settings, parent, source, scored, files_of)
    res.submission = entry
    return res


def plausible(layout: Layout, path: Path, aligned: dict, tests: dict) -> float:
    """The file's speed factor (benchmark/release/submission.py ``check_plausible``) over every test
    sequence, against what Train's ground truth shows; SubmissionError beyond the limit."""
    from skidbench.pipeline.core.schema import read_split

    vels, cmds = [], []
    for terrain, sp in tests.items():
        for split, seqs in sp.items():
            vels += list(aligned[terrain][split][0])
            cmds += [s.table[["cmd_v", "cmd_w"]] for s in seqs]
    train = [read_split(p)[0] for t in tests for p in split_files(layout, t, TRAIN)]
    return sb.check_plausible(str(path), vels, cmds, sb.train_scales(train))


@dataclass
class CheckResult:
    path: Path
    protocol: str
    sequences: int
    rows: int
    factor: float
    against: str  # what the file was checked against


def public_tests(
    layout: Layout, splits: list[str], protocol: str
) -> dict[str, dict[str, list[TestSequence]]]:
    """The test sequences of a dataset imported from a public half: its CV/LD model-input tables (the
    clock, the commands; no truth), per terrain and split."""
    from skidbench.pipeline.datasets.imported import RECORD_DIR

    base = layout.root / RECORD_DIR / "inputs" / protocol
    if not base.is_dir():
        have = sorted(p.name for p in base.parent.iterdir()) if base.parent.is_dir() else []
        raise PredictionsError(f"{base}: no model inputs of inputs={protocol} in this public half (it has: "
                               f"{', '.join(have) or 'none'})")  # fmt: skip
    tests: dict[str, dict[str, list[TestSequence]]] = {}
    for terrain_dir in sorted(p for p in base.iterdir() if p.is_dir()):
        for split in splits:
            for f in sorted((terrain_dir / split).glob("*.parquet")):
                table = pd.read_parquet(f)
                seq = str(table["sequence"].iloc[0]) if len(table) else f.stem
                tests.setdefault(terrain_dir.name, {}).setdefault(split, []).append(
                    TestSequence(seq, f, table, {})
                )
    return tests


def check_predictions(layout: Layout, path: Path, protocol: str = "commanded") -> CheckResult:
    """``score.check=true``: the file checked as score checks it (sequences, rows, times, values,
    plausible speeds) against the test sequences, scoring nothing: from the split files, or for a dataset
    imported from a public half, from its model-input tables."""
    from skidbench.benchmark.release.bundle import read_bundle_doc
    from skidbench.pipeline.datasets.imported import truth_withheld

    path = Path(path).expanduser().absolute()
    protocol = check_protocol(protocol)
    doc = read_bundle_doc(layout.root / "bundle") or {}
    splits = [str(s) for s in (doc.get("metric") or {}).get("splits") or evaluate_defaults()["splits"]]
    if truth_withheld(layout.root):
        tests, against = public_tests(layout, splits, protocol), "the public half's model inputs"
    else:
        tests, against = _tests(layout, splits, None)[0], "the split files"
    preds = read_predictions(path)
    aligned = align(path, preds, tests)
    factor = plausible(layout, path, aligned, tests)
    n = sum(len(s) for sp in tests.values() for s in sp.values())
    return CheckResult(path, protocol, n, len(preds), factor, against)


def format_check(res: CheckResult) -> str:
    return (
        f"score: {res.path.name}: a valid predictions file under inputs={res.protocol} ({res.sequences} test "
        f"sequences, {res.rows} rows, every clock as in {res.against}; speeds {res.factor:.2f} times the "
        "commanded at most); nothing scored (score.check=true)"
    )


def reproduce_command(dataset: str, path: Path, protocol: str, entry: sb.Submission) -> str:
    """The command that scores the entry again (the predictions file by its name: a reader's own copy)."""
    return (f"skidbench score {dataset} --predictions {Path(path).name} inputs={protocol} "
            f"score.name={entry.name} score.link={shlex.quote(entry.link)} "
            f"score.submitter={shlex.quote(entry.submitter)} score.date={entry.date}")  # fmt: skip


def _child_tags(entry: sb.Submission, terrain: str, digest: str) -> dict[str, str]:
    """The tags of an external child run: what it is, the predictions' digest and the entry's identity."""
    return {
        run_tags.TAG_ROLE: "child",
        run_tags.TAG_MODEL: entry.name,
        run_tags.TAG_TERRAIN: terrain,
        run_tags.TAG_MODEL_VERSION: EXTERNAL_VERSION,
        run_tags.TAG_PLUGIN: f"external predictions sha256:{digest[:12]}",
        run_tags.TAG_EXTERNAL: "true",
        run_tags.TAG_PREDICTIONS_SHA256: digest,
        **entry.tags(),
    }


def _log(
    layout, tracker, path, entry, protocol, digest, settings, parent, source, scored, files_of
) -> ScoreResult:
    from mlflow.exceptions import MlflowException

    name = entry.name
    cmd = reproduce_command(layout.dataset, path, protocol, entry)
    common = {
        run_tags.TAG_DATASET: layout.dataset,
        **environment.run_tags(),
        run_tags.TAG_GIT: environment.git_commit(),
        run_tags.TAG_INPUTS: protocol,
    }
    params = {
        "splits": str(settings["splits"]),
        "horizons": str([float(h) for h in settings["horizons"]]),
        "min_distance_m": str(settings["min_distance_m"]),
        "min_rotation_deg": str(settings["min_rotation_deg"]),
        "predictions": Path(path).name,
        "predictions_sha256": digest,
        "inputs": protocol,
        "model": name,
    }
    rows = []
    try:
        own_parent = parent is None
        if own_parent:
            parent = tracker.start(
                tracker.unique_run_name(run_tags.parent_run_name("score", layout.dataset, protocol)),
                {
                    **common,
                    run_tags.TAG_ROLE: "parent",
                    "skidbench.models": name,
                    "skidbench.terrains": ",".join(scored),
                    run_tags.TAG_NOTE: run_tags.describe(
                        f"External predictions **{name}** scored on {layout.dataset}",
                        {"input protocol": f"`{protocol}`", "settings from": source},
                        cmd,
                    ),
                },
            )
            tracker.log(parent, params={k: v for k, v in params.items() if k in rt.SETTING_KEYS})
        base = _facts(layout, tracker, parent, entry, protocol, digest, settings, cmd, common)
        results = rt.Writer(layout, parent, f"score-{digest[:12]}-{brd.utc_stamp()}")
        with results.until_done():
            rows = _log_children(layout, tracker, path, entry, protocol, digest, source, cmd, common, params,
                                 parent, scored, files_of, base, results)  # fmt: skip
        if own_parent:
            tracker.log(
                parent,
                metrics={"n_children": len(rows), "n_failed": 0},
                tags={run_tags.TAG_STATUS: "FINISHED"},
            )
            tracker.end(parent, "FINISHED")
        tracker.artifact(parent, results.path, "results")
    except MlflowException as exc:
        raise EvaluationError(f"MLflow store {tracker.uri}: {one_line(exc.message)[:300]}") from None
    return ScoreResult(name, protocol, digest, parent, rows, source, float(settings["horizons"][0]))


def _log_children(
    layout, tracker, path, entry, protocol, digest, source, cmd, common, params, parent, scored, files_of,
    base: rt.RunFacts, results: rt.Writer,
) -> list[dict[str, Any]]:  # fmt: skip
    """One external child run per terrain of ``parent`` (tags, params, its windows, its rows of the results
    table and the MLflow metrics logged from them); returns per terrain its run id and metrics."""
    name, rows = entry.name, []
    for terrain, (scores, windows) in scored.items():
        facts = {
            "predictions": f"`{Path(path).name}` (sha256 `{digest}`)",
            "submitted": f"by {entry.submitter} on {entry.date}: {entry.link}",
            "input protocol": f"`{protocol}`",
            "terrain": terrain,
            "settings from": source,
            "metrics": mt.describe() + " (what evaluate logs)",
        }
        tags = {**common, **_child_tags(entry, terrain, digest), run_tags.TAG_NOTE: run_tags.describe(
            f"External predictions **{name}** on **{terrain}**", facts, cmd),
            run_tags.TAG_FINGERPRINT: split_fingerprint(files_of[terrain], layout.splits)}  # fmt: skip
        run_id = tracker.start(
            f"{name}/{terrain}" + ("" if protocol == "commanded" else f" [{protocol}]") + " (external)",
            tags,
            parent,
        )
        tracker.log(run_id, params={**params, "terrain": terrain})
        run = replace(base, run_id=run_id, terrain=terrain, start_time=dt.datetime.now(dt.UTC),
                      splits_fingerprint=tags[run_tags.TAG_FINGERPRINT])  # fmt: skip
        metrics = _write_scores(layout, tracker, results, run, windows, scores)
        tracker.log(run_id, metrics=metrics, tags={run_tags.TAG_STATUS: "FINISHED"})
        tracker.end(run_id, "FINISHED")
        rows.append({"terrain": terrain, "run_id": run_id, **metrics})
    return rows


def _write_scores(
    layout: Layout, tracker: trk.Tracker, results: rt.Writer, facts: rt.RunFacts, windows: pd.DataFrame,
    scores: list[Score],
) -> dict[str, float]:  # fmt: skip
    """An external run's windows (``<stem>.windows.parquet``, logged to the run) and its rows of the results
    table; returns its MLflow metrics (logged from the rows, as evaluate's)."""
    stem = layout.eval_stem(facts.model, facts.terrain, facts.inputs)
    win = stem.with_name(stem.name + ".windows.parquet")
    write_parquet_atomic(pa.Table.from_pandas(windows, preserve_index=False), win,
                         {"model": facts.model, "terrain": facts.terrain, "run_id": facts.run_id,
                          "inputs": facts.inputs, "external": True,
                          "predictions_sha256": facts.predictions_sha256})  # fmt: skip
    tracker.artifact(facts.run_id, win, "windows")
    new = rt.rows(facts, scores)
    results.add(new)
    return rt.mlflow_metrics(pd.DataFrame(new))


def _facts(layout, tracker, parent, entry, protocol, digest, settings, cmd, common) -> rt.RunFacts:
    """What every row of a scored predictions file carries (benchmark/board/results.py): the board's
    settings, the dataset, the environment and the submission's identity."""
    env = "skidbench.env."
    return rt.RunFacts(
        evaluate_id=parent, run_id="", model=entry.name, inputs=protocol, terrain="", external=True,
        min_distance_m=float(settings["min_distance_m"]),
        min_rotation_deg=float(settings["min_rotation_deg"]),
        horizons=[float(h) for h in settings["horizons"]], splits=[str(x) for x in settings["splits"]],
        models=[entry.name], dataset=layout.dataset, dataset_id=tracker.dataset_id or "",
        experiment=tracker.experiment_name, model_version=EXTERNAL_VERSION,
        package=f"external predictions sha256:{digest[:12]}",
        skidbench_version=common.get("skidbench.version", ""), git_commit=common.get(run_tags.TAG_GIT, ""),
        versions={k[len(env):]: str(v) for k, v in common.items() if k.startswith(env)},
        user=run_tags.current_user(), reproduce=cmd, predictions_sha256=digest, link=entry.link,
        submitter=entry.submitter, submitted=entry.date, description=entry.description,
    )  # fmt: skip


def format_score(res: ScoreResult) -> str:
    horizon = res.horizon
    if res.already:
        return (f"score: {res.name}: these predictions (sha256 {res.sha256[:16]}...) are already this entry "
                f"of the inputs={res.protocol} board; nothing logged")  # fmt: skip
    lines = [
        f"score: {res.name} (external, sha256 {res.sha256[:16]}...) under inputs={res.protocol}; settings "
        "from "
        f"{res.settings_from}; parent run {res.parent_run_id}",
        *(
            [f"submitted by {res.submission.submitter} on {res.submission.date}: {res.submission.link}"]
            if res.submission
            else []
        ),
    ]
    cols = [(m.metric_key(s, horizon), f"{s}_{horizon:g}s_{m.short} {m.label_unit}".rstrip())
            for s in ("cv", "ld") for m in mt.HEADLINE]  # fmt: skip
    lines.append("terrain  " + "  ".join(lab for _, lab in cols))
    for r in res.rows:
        lines.append(
            f"{r['terrain']:<8} " + "  ".join(f"{r.get(k, float('nan')):>{len(lab)}.2f}" for k, lab in cols)
        )
    lines.append("`skidbench compare` ranks it with the evaluated models (same dataset, same protocol).")
    return "\n".join(lines)
