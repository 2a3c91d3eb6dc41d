"""Results keyed by what made them: which (model, terrain) runs an evaluate takes, unchanged, from an earlier
complete evaluate instead of running them again, and why it runs the others again.

A model run's *result key* (tag ``skidbench.result_key``) is the fingerprint of what its numbers are made of:

- ``fit``: the key of its fit (``fit_stamp`` of models/fitting/fit.py: the Train files, the model's config,
  its code (distribution, version and the digest of the files it runs: an edit without a version bump
  counts), the robot, the calibration, the input protocol);
- ``code``: the model's code (in the fit's key too; apart, to say what changed);
- ``scoring``: the digest of the scoring code (:data:`SCORING_CODE`; tag ``skidbench.scoring_digest``);
- ``data``: the fingerprint of the terrain's split files;
- ``settings``: the evaluate's config but its model and terrain lists, the store, ``force`` and a model's
  command-line options (in that model's fit key).

When the run finishes it is stamped (``<ds>/.stamps/evaluate/<protocol>/<model>/<terrain>.json``,
pipeline/core/cache.py) with its outputs (the per-window table, the fitted parameters and the report data
compare reads) and its run and evaluate. The next evaluate (without ``force=true``) takes that run as it is
when the key is the same, its outputs are intact, its rows are in the results table and the run FINISHED in
this store and experiment, whether its evaluate finished or was killed or failed after it (a run is stamped
only once it FINISHED, its rows written: it is complete; an evaluate still RUNNING is not taken from). The
new evaluate carries the runs it takes: its parent run lists them (tag ``skidbench.reused_runs``) and its
results file holds their rows under its own ``evaluate_id`` (evaluate/evaluation.py), so its board is the
whole board; the runs of a killed evaluate are on a board only so, never as that evaluate's.
Every model run again for a reason says so in one line (``evaluate: friction: its code changed (digest a -> b)
since run 1a2b3c4d; run again on 3 terrain(s)``: refitted, as its fit's key holds its code, and scored)."""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
import pyarrow as pa

from skidbench.benchmark.board import results as rt
from skidbench.benchmark.evaluate.settings import EvaluateSettings
from skidbench.benchmark.evaluate.testsets import split_fingerprint
from skidbench.models.fitting.fit import FitSettings, fit_stamp
from skidbench.pipeline.core.cache import Stamp, stamp_file
from skidbench.pipeline.core.io import fingerprint_obj
from skidbench.pipeline.runner.environment import code_change, tree_digest

TAG_RESULT_KEY = "skidbench.result_key"
TAG_SCORING = "skidbench.scoring_digest"
TAG_REUSED = "skidbench.reused_runs"  # a parent run: the runs of earlier evaluates its board takes
#: the ends of an evaluate whose FINISHED runs are taken: complete, or stopped after them (killed, failed)
ENDED = ("FINISHED", "KILLED", "FAILED")
#: the code that turns a model's predictions into the logged numbers: the scoring package (windows, metrics,
#: intervals, the floor), the test sets, and the inputs a model is given at predict time
SCORING_CODE = (
    "skidbench.benchmark.scoring",  # a package: every file of its folder
    "skidbench.benchmark.evaluate.testsets",
    "skidbench.pipeline.core.protocol",
)
#: config entries that say how to run or which units, not what a unit's numbers are made of (``model``: the
#: ``+model.*`` overrides of one model, which its fit's key holds)
NOT_SETTINGS = ("models", "extra_models", "terrains", "force", "mlflow", "hydra", "model")


def scoring_digest() -> str:
    """The digest of the files of :data:`SCORING_CODE` (a package: every file of its folder; an edit of any of
    them scores every model again)."""
    digests = []
    for name in SCORING_CODE:
        module = importlib.import_module(name)
        path = Path(module.__file__)
        root = path.parent if path.name == "__init__.py" else path
        digests.append(tree_digest(root)[0])
    return fingerprint_obj(digests)


@dataclass
class ResultKey:
    """The result key of one (model, terrain) of an evaluate and the stamp it is recorded in."""

    model: str
    terrain: str
    key: str
    stamp: Stamp

    @property
    def made_of(self) -> dict[str, Any]:
        return self.stamp.made_of(self.key).get("config") or {}


def result_key(
    fit: FitSettings, conf: dict[str, Any], model: str, terrain: str, protocol: str, data_fingerprint: str
) -> ResultKey | None:
    """The :class:`ResultKey` of ``model`` on ``terrain`` under ``protocol``; None when its fit cannot be
    planned (a model that is not installed, a terrain without a response: its run says why)."""
    try:
        fstamp, fit_key = fit_stamp(fit, model, terrain)
    except Exception:  # noqa: BLE001 - the model's run reports its own problem
        return None
    code = (fstamp.made_of(fit_key).get("config") or {}).get("code")
    settings = {k: v for k, v in conf.items() if k not in NOT_SETTINGS}
    made = {"fit": fit_key, "code": code, "scoring": scoring_digest(), "data": data_fingerprint,
            "settings": settings}  # fmt: skip
    stamp = Stamp(stamp_file(fit.layout.root, "evaluate", protocol, model, f"{terrain}.json"), "evaluate")
    return ResultKey(model, terrain, stamp.key([], made), stamp)


def why_again(rk: ResultKey) -> str | None:
    """Why the recorded run of ``rk`` cannot be taken because what made it changed (None: it never ran, or
    nothing changed)."""
    if not rk.stamp.data:
        return None
    changed = rk.stamp.changed(rk.key)
    since = f" since run {str((rk.stamp.data.get('info') or {}).get('run_id', '?'))[:8]}"
    if "code" in changed:
        return code_change(changed) + since
    if "scoring" in changed:
        a, b = (str(x)[:12] for x in changed["scoring"])
        return f"the scoring code changed (digest {a} -> {b}){since}"
    if "data" in changed:
        return f"its split files changed{since}"
    if "fit" in changed:
        return f"its fit's inputs changed (Train files, config, robot or calibration){since}"
    if "settings" in changed:
        then, now = ((x or {}) for x in changed["settings"])
        keys = sorted(k for k in {*then, *now} if fingerprint_obj(then.get(k)) != fingerprint_obj(now.get(k)))
        return f"the evaluate's settings changed ({', '.join(keys)}){since}"
    if rk.stamp.data.get("key") != rk.key:
        return f"its earlier result was recorded differently (an older skidbench){since}"
    why = rk.stamp.outputs_reason()
    return f"{why}{since}" if why else None


def earlier_run(
    rk: ResultKey, tracker: Any, in_table: set[str] | None = None, parents: dict[str, Any] | None = None
) -> tuple[Any | None, str | None]:
    """``(run, None)``: the earlier run of ``rk`` to take as it is; ``(None, why)``: why it runs again (why
    None: it never ran here). ``in_table``: the run ids the dataset's results table has rows of (None: not
    checked); ``parents``: the evaluate runs read so far, by id (read once each, and added to)."""
    why = why_again(rk)
    if why is not None or not rk.stamp.data:
        return None, why
    info = rk.stamp.data.get("info") or {}
    run_id, parent_id = str(info.get("run_id", "")), str(info.get("parent_run_id", ""))
    if info.get("tracking_uri") != tracker.uri or info.get("experiment") != tracker.experiment_name:
        return None, f"its run {run_id[:8]} is in another store or experiment ({info.get('tracking_uri')})"
    from mlflow.exceptions import MlflowException

    parents = {} if parents is None else parents
    try:
        run = tracker.client.get_run(run_id)
        parent = parents.get(parent_id) or parents.setdefault(parent_id, tracker.client.get_run(parent_id))
    except MlflowException:
        return None, f"its run {run_id[:8]} or its evaluate {parent_id[:8]} is gone from the store"
    if run.info.lifecycle_stage != "active" or run.info.status != "FINISHED":
        return None, f"its run {run_id[:8]} is {run.info.status} ({run.info.lifecycle_stage})"
    if parent.info.status not in ENDED or parent.info.lifecycle_stage != "active":
        return None, (
            f"its run {run_id[:8]} is of evaluate {parent.info.run_name} ({parent_id[:8]}), which is "
            f"{parent.info.status} ({parent.info.lifecycle_stage})"
        )
    if tracker.dataset_id and run.data.tags.get("skidbench.dataset_id") != tracker.dataset_id:
        return None, f"its run {run_id[:8]} is of another dataset with this name"
    if in_table is not None and run_id not in in_table:
        return None, f"its run {run_id[:8]} has no rows in the results table"
    return run, None


def record(rk: ResultKey, outputs: Sequence[Path], run_id: str, parent_id: str, tracker: Any) -> None:
    """Stamp a FINISHED run of ``rk`` (after its outputs are written and logged)."""
    info = {"run_id": run_id, "parent_run_id": parent_id, "tracking_uri": tracker.uri,
            "experiment": tracker.experiment_name}  # fmt: skip
    rk.stamp.record(rk.key, [p for p in outputs if Path(p).is_file()], info)


@dataclass
class ReusePlan:
    """What an evaluate takes from earlier evaluates: ``(model, terrain) -> run`` taken, their rows of the
    results table (``rows``, to carry in the new evaluate's file), ``(model, terrain) -> result key`` of the
    runs it makes, why each model runs again, and the evaluates taken from that did not finish
    (``unfinished``: ``<name> (<id8>) ended KILLED`` per run taken from one)."""

    taken: dict[tuple[str, str], Any] = field(default_factory=dict)
    keys: dict[tuple[str, str], ResultKey] = field(default_factory=dict)
    again: dict[str, list[str]] = field(default_factory=dict)  # model -> why, per terrain run again
    rows: pd.DataFrame = field(default_factory=pd.DataFrame)
    unfinished: dict[tuple[str, str], str] = field(default_factory=dict)

    def carried(self, run_id: str, evaluate_id: str, models: Sequence[str]) -> list[dict[str, Any]]:
        """The results-table rows of the taken run ``run_id`` as rows of the evaluate ``evaluate_id`` (its
        id and model list; its status is written when it ends)."""
        rows = self.rows[self.rows["run_id"] == run_id] if len(self.rows) else self.rows
        if len(rows):  # one evaluate's copy (a run taken before is in the file of each evaluate it is in)
            rows = rows[rows["evaluate_id"] == rows["evaluate_id"].iloc[0]]
        return [{**r, "evaluate_id": evaluate_id, "models": list(models)} for r in records(rows)]

    def tags(self) -> dict[str, str]:
        """The parent run's tag naming the runs taken (none when it took none)."""
        return {TAG_REUSED: ",".join(r.info.run_id for r in self.taken.values())} if self.taken else {}

    def lines(self) -> list[str]:
        """One line per model run again for a reason, and one for the runs taken."""
        out = []
        for model, whys in self.again.items():
            out.append(f"evaluate: {model}: {whys[0]}; run again on {len(whys)} terrain(s)")
        if self.taken:
            names = ", ".join(f"{m}/{t}" for m, t in self.taken)
            out.append(
                f"evaluate: {len(self.taken)} model run(s) unchanged since an earlier evaluate (same code, "
                f"data and settings) taken as they are: {names} (force=true runs them again)"
            )
        for ended in dict.fromkeys(self.unfinished.values()):
            names = ", ".join(f"{m}/{t}" for (m, t), e in self.unfinished.items() if e == ended)
            out.append(f"evaluate: {names}: finished in evaluate {ended}; taken into this one, the board's")
        return out


#: the columns of the results table that are not floats (a null one is read as NaN)
_NOT_FLOAT = [f.name for f in rt.SCHEMA if not pa.types.is_floating(f.type)]


def records(rows: pd.DataFrame) -> list[dict[str, Any]]:
    """Rows read from the results table (:func:`results.read`) as the records its writer takes (a null
    integer or string None, not NaN)."""
    out = rows.to_dict("records")
    for r in out:
        r.update({k: None for k in _NOT_FLOAT if isinstance(r.get(k), float) and r[k] != r[k]})
    return out


def plan_reuse(
    es: EvaluateSettings, tracker: Any, files_of: dict[str, list[Path]], terrains: Sequence[str]
) -> ReusePlan:
    """The :class:`ReusePlan` of the evaluate ``es`` on ``terrains`` (``files_of``: each one's split files),
    said on the console (:meth:`ReusePlan.lines`); with ``force``, nothing taken, every run made again."""
    plan = ReusePlan()
    try:
        table = rt.read(es.layout)
    except rt.ResultsTableError:  # a damaged results file: nothing taken, every run made again
        table = rt.SCHEMA.empty_table().to_pandas()
    table = table[table["role"] == rt.MODEL]
    in_table, parents = set(table["run_id"]), {}
    for terrain in terrains:
        fingerprint = split_fingerprint(files_of[terrain], es.layout.splits)
        for model in es.models:
            rk = result_key(es.fit, es.conf, model, terrain, es.protocol, fingerprint)
            if rk is None:
                continue
            run, why = (None, None) if es.force else earlier_run(rk, tracker, in_table, parents)
            if run is not None:
                plan.taken[(model, terrain)] = run
                parent = parents[str(rk.stamp.data["info"]["parent_run_id"])]
                if parent.info.status != "FINISHED":
                    plan.unfinished[(model, terrain)] = (
                        f"{parent.info.run_name} ({parent.info.run_id[:8]}) ended {parent.info.status}"
                    )
            else:
                plan.keys[(model, terrain)] = rk
                if why:
                    plan.again.setdefault(model, []).append(why)
    taken = {r.info.run_id for r in plan.taken.values()}
    plan.rows = table[table["run_id"].isin(taken)].reset_index(drop=True)
    for line in plan.lines():
        print(line, flush=True)
    return plan
