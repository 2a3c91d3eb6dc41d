"""The results table: every score of a dataset, written once where it is computed (docs/results-table.md).

``evaluate`` (and ``score`` for a predictions file) writes one Parquet file per parent run,
``<out_root>/<dataset>/results/<evaluate_id>.parquet``, rewritten atomically after each model run (so an
interrupted evaluate keeps the rows of the runs it finished, and two evaluates at once write apart) and
once more when the evaluate ends (its ``evaluate_status``). One row per (run, model, input protocol,
horizon, split, terrain, metric, stratum): the estimate, its interval and the windows and independent
blocks behind it, the run's status and fit numbers, the settings it was scored with and its provenance.

MLflow's metrics are logged from these rows (:func:`mlflow_metrics`: the keys the UI shows,
``ld_6s_trans_rmsre_pct``), and compare, export, publish and score read the table (:func:`read`,
:func:`runs`, :func:`board`), not MLflow's strings. The schema (:data:`SCHEMA`, :data:`SCHEMA_VERSION`) is
a contract: a column added is a minor version, a column changed or removed a major one; a file with a
column missing or of another type is refused in one line naming the file and the column.
"""

from __future__ import annotations

import contextlib
import datetime as dt
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring.predictions import Score, keyed
from skidbench.pipeline.core.errors import one_line
from skidbench.pipeline.core.io import write_parquet_atomic
from skidbench.pipeline.core.layout import Layout

SCHEMA_VERSION = "1.1"  # 1.1: the stratum rows (benchmark/board/strata.py)
#: the Parquet metadata key of the schema version
VERSION_KEY = "skidbench.results_schema"
ALL = "all"  # the stratum of every window (the others: benchmark/board/strata.py)
MODEL, REFERENCE = "model", "floor"  # the rows' roles: a model's run, or the floor of a terrain

_S, _F, _I, _B = pa.string(), pa.float64(), pa.int64(), pa.bool_()
#: the columns, in order (docs/results-table.md says what each is)
SCHEMA = pa.schema([
    ("evaluate_id", _S), ("run_id", _S), ("role", _S), ("model", _S), ("inputs", _S), ("horizon_s", _F),
    ("split", _S), ("terrain", _S), ("metric", _S), ("stratum", _S),
    ("estimate", _F), ("lo", _F), ("hi", _F), ("n_windows", _I), ("n_blocks", _I),
    ("seed_sd", _F), ("seed_min", _F), ("seed_max", _F), ("n_seeds", _I),
    ("status", _S), ("reason", _S), ("evaluate_status", _S), ("external", _B), ("imported", _B),
    ("start_time", pa.timestamp("ms", tz="UTC")),
    ("fit_loss", _F), ("fit_time_s", _F), ("predict_time_s", _F),
    ("min_distance_m", _F), ("min_rotation_deg", _F), ("horizons", pa.list_(_F)), ("splits", pa.list_(_S)),
    ("models", pa.list_(_S)),
    ("dataset", _S), ("dataset_id", _S), ("experiment", _S), ("splits_fingerprint", _S),
    ("options_digest", _S),
    ("model_version", _S), ("package", _S), ("code_distribution", _S), ("code_version", _S),
    ("code_digest", _S), ("scoring_digest", _S), ("result_key", _S), ("skidbench_version", _S),
    ("git_commit", _S), ("versions", pa.map_(_S, _S)), ("user", _S), ("reproduce", _S),
    ("predictions_sha256", _S), ("link", _S), ("submitter", _S), ("submitted", _S), ("description", _S),
])  # fmt: skip
#: the run-level columns (equal on every row of one run)
RUN_COLUMNS = tuple(SCHEMA.names[SCHEMA.names.index("status") :])


class ResultsTableError(EvaluationError):
    """A results file that is not a results table of this schema (one line: the file and the column)."""


@dataclass
class RunFacts:
    """What every row of one run carries: who it is, how it ended, what it was scored with and where it
    comes from (the run-level columns of :data:`SCHEMA`)."""

    evaluate_id: str
    run_id: str
    model: str
    inputs: str
    terrain: str
    role: str = MODEL
    status: str = "FINISHED"
    reason: str = ""
    evaluate_status: str = "RUNNING"
    external: bool = False
    imported: bool = False
    start_time: dt.datetime = field(default_factory=lambda: dt.datetime.now(dt.UTC))
    fit_loss: float = float("nan")
    fit_time_s: float = float("nan")
    predict_time_s: float = float("nan")
    min_distance_m: float = float("nan")
    min_rotation_deg: float = float("nan")
    horizons: list[float] = field(default_factory=list)
    splits: list[str] = field(default_factory=list)
    models: list[str] = field(default_factory=list)
    dataset: str = ""
    dataset_id: str = ""
    experiment: str = ""
    splits_fingerprint: str = ""
    options_digest: str = ""
    model_version: str = ""
    package: str = ""
    code_distribution: str = ""
    code_version: str = ""
    code_digest: str = ""
    scoring_digest: str = ""
    result_key: str = ""
    skidbench_version: str = ""
    git_commit: str = ""
    versions: dict[str, str] = field(default_factory=dict)
    user: str = ""
    reproduce: str = ""
    predictions_sha256: str = ""
    link: str | None = None
    submitter: str | None = None
    submitted: str | None = None
    description: str | None = None

    def fitted(self, metrics: dict, version: object, package: str, code: object) -> None:
        """The fit's numbers (``metrics``' ``fit_loss``, ``fit_time_s``), the model's version, package and
        code (a ``CodeIdentity``: distribution, version, digest)."""
        self.fit_loss, self.fit_time_s = (float("nan") if metrics.get(k) is None else float(metrics[k])
                                          for k in ("fit_loss", "fit_time_s"))  # fmt: skip
        self.model_version, self.package = str(version), str(package)
        self.code_distribution, self.code_version, self.code_digest = (
            code.distribution,
            code.version,
            code.digest,
        )


def headline(rows_: pd.DataFrame) -> str:
    """The headline cells of a run's rows by their MLflow names (the log line of a finished run)."""
    out = []
    for r in rows_.itertuples(index=False):
        m = mt.get(r.metric)
        if m.headline:
            out.append(f"{m.metric_key(r.split, r.horizon_s)}={r.estimate:.4g}")
    return ", ".join(out)


def rows(
    facts: RunFacts,
    scores: Sequence[Score],
    seeds: dict[tuple[str, str, float], tuple[float, float, float]] | None = None,
    n_seeds: int | None = None,
) -> list[dict]:
    """The rows of one run: one per cell of ``scores`` (stratum :data:`ALL`), with the run's facts and,
    for a model fitted over several seeds, each cell's ``(sd, min, max)`` over them (``seeds``)."""
    run = asdict(facts)
    out = []
    for s in scores:
        spread = (seeds or {}).get((s.metric, s.split, s.horizon_s))
        out.append({**run, "horizon_s": float(s.horizon_s), "split": s.split, "metric": s.metric,
                    "stratum": ALL, "estimate": float(s.estimate), "lo": float(s.lo), "hi": float(s.hi),
                    "n_windows": int(s.n_windows), "n_blocks": s.n_blocks,
                    "seed_sd": spread[0] if spread else None, "seed_min": spread[1] if spread else None,
                    "seed_max": spread[2] if spread else None,
                    "n_seeds": n_seeds if seeds is not None else None})  # fmt: skip
    return out


def empty_scores(splits: Sequence[str], horizons: Sequence[float]) -> list[Score]:
    """The cells of a run without scores (it failed or was killed before it scored): every metric that is
    always scored, on every test split and horizon, without a value."""
    nan = float("nan")
    return [Score(m.name, sp, float(h), nan, 0) for h in horizons for sp in splits for m in mt.METRICS
            if not m.optional]  # fmt: skip


def unscored(
    facts: RunFacts, splits: Sequence[str], horizons: Sequence[float], status: str, reason: str
) -> list[dict]:
    """The rows of a run without scores (``status``: RUNNING when it starts, FAILED or KILLED when it
    ended before it was scored; ``reason``): its cells without a value (:func:`empty_scores`)."""
    return rows(replace(facts, status=status, reason=one_line(str(reason))), empty_scores(splits, horizons))


def to_table(records: Sequence[dict]) -> pa.Table:
    """Rows as a table of :data:`SCHEMA` (NaN kept as NaN in float columns; None is null)."""
    cols = {}
    for f in SCHEMA:
        values = [r.get(f.name) for r in records]
        if f.name == "versions":
            values = [list((v or {}).items()) for v in values]
        cols[f.name] = pa.array(values, type=f.type, from_pandas=False)
    return pa.table(cols, schema=SCHEMA.with_metadata({VERSION_KEY: SCHEMA_VERSION}))


def folder(layout: Layout) -> Path:
    """``<out_root>/<dataset>/results``: the dataset's results files."""
    return layout.root / "results"


class Writer:
    """The results file of one evaluate (or score) run: :meth:`add` a run's rows (the file rewritten
    atomically with every row so far), :meth:`finish` with the evaluate's end status."""

    def __init__(self, layout: Layout, evaluate_id: str, name: str | None = None) -> None:
        """``name``: the file's name without ``.parquet`` (default: ``evaluate_id``; score's rows hang from
        an evaluate's run but have a file of their own)."""
        self.path = folder(layout) / f"{name or evaluate_id}.parquet"
        self.records: list[dict] = []

    def add(self, records: Sequence[dict]) -> None:
        """Writes ``records``, in place of the rows already written of the same runs (a run's RUNNING
        rows, written when it starts, give way to its scores)."""
        key = lambda r: (r["run_id"], r["model"], r["terrain"])  # noqa: E731 (the floor's: one run per terrain)
        new = {key(r) for r in records}
        self.records = [r for r in self.records if key(r) not in new] + list(records)
        self._write()

    def add_strata(self, records: Sequence[dict]) -> None:
        """Writes stratum rows (``stratum`` other than :data:`ALL`) of runs already written, in place of
        their earlier stratum rows."""
        key = lambda r: (r["run_id"], r["model"], r["terrain"])  # noqa: E731
        new = {key(r) for r in records}
        self.records = [r for r in self.records if r["stratum"] == ALL or key(r) not in new] + list(records)
        self._write()

    @contextlib.contextmanager
    def until_done(self, finished: Callable[[Path], None] | None = None) -> Iterator[None]:
        """The block of the evaluate: the file ends with its status (FINISHED, FAILED, or KILLED on an
        interrupt); ``finished(path)`` is called when it FINISHED (evaluate logs the file to its run)."""
        try:
            yield
        except KeyboardInterrupt:
            self.finish("KILLED")
            raise
        except BaseException:
            self.finish("FAILED")
            raise
        path = self.finish("FINISHED")
        if finished is not None:
            finished(path)

    def finish(self, status: str) -> Path:
        for r in self.records:
            r["evaluate_status"] = status
        self._write()
        return self.path

    def _write(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_parquet_atomic(to_table(self.records), self.path)


def check(path: Path, schema: pa.Schema) -> None:
    """ResultsTableError (one line) when a file's schema is not a results table's: another major version,
    a column missing or of another type (a column added by a newer minor version is read and ignored)."""
    meta = schema.metadata or {}
    version = (meta.get(VERSION_KEY.encode()) or b"").decode() or "?"
    if version.split(".")[0] != SCHEMA_VERSION.split(".")[0]:
        raise ResultsTableError(
            f"{path}: results table schema {version}, this skidbench reads {SCHEMA_VERSION} (major versions "
            "differ); evaluate again with this version"
        )
    for f in SCHEMA:
        if f.name not in schema.names:
            raise ResultsTableError(
                f"{path}: column {f.name!r} missing (results table schema {SCHEMA_VERSION})"
            )
        got = schema.field(f.name).type
        if got != f.type:
            raise ResultsTableError(f"{path}: column {f.name!r} is {got}, expected {f.type}")


def read(layout: Layout) -> pd.DataFrame:
    """Every row of the dataset's results files (empty frame of :data:`SCHEMA`'s columns when there is
    none); ResultsTableError (one line) for a file that is not a results table (:func:`check`)."""
    tables = []
    for path in sorted(folder(layout).glob("*.parquet")):
        try:
            schema = pq.read_schema(path)
        except Exception as exc:  # noqa: BLE001 - not Parquet, truncated: one line
            raise ResultsTableError(f"{path}: not a results table ({type(exc).__name__}: {exc})") from None
        check(path, schema)
        tables.append(pq.read_table(path, columns=SCHEMA.names))
    if not tables:
        return SCHEMA.empty_table().to_pandas()
    table = pa.concat_tables([t.cast(SCHEMA) for t in tables])
    df = table.to_pandas()
    df["versions"] = [dict(v) if v is not None else {} for v in df["versions"]]
    return df


# -- what the rows are in MLflow ---------------------------------------------------------------------------
def scores_of(rows_: pd.DataFrame) -> list[Score]:
    """The cells of rows (of one run) as :class:`Score` (an interval only where blocks were counted)."""
    out = []
    for r in rows_.itertuples(index=False):
        blocks = None if pd.isna(r.n_blocks) else int(r.n_blocks)
        out.append(Score(r.metric, r.split, float(r.horizon_s), float(r.estimate), int(r.n_windows),
                         float(r.lo), float(r.hi), blocks))  # fmt: skip
    return out


def mlflow_metrics(rows_: pd.DataFrame) -> dict[str, float]:
    """The MLflow metrics of one run's rows, by the names the UI shows: every cell's value, window count,
    interval and blocks (:func:`scoring.keyed`), ``predict_time_s``, and for a model fitted over several
    seeds ``n_seeds`` and each cell's ``<key>_seed_sd``, ``_seed_min``, ``_seed_max``."""
    if not len(rows_):
        return {}
    out = keyed(scores_of(rows_))
    first = rows_.iloc[0]
    if first["role"] == MODEL and pd.notna(first["predict_time_s"]):
        out["predict_time_s"] = float(first["predict_time_s"])
    if pd.notna(first["n_seeds"]):
        out["n_seeds"] = float(first["n_seeds"])
        for r in rows_[rows_["seed_sd"].notna()].itertuples(index=False):
            key = mt.get(r.metric).metric_key(r.split, r.horizon_s)
            out[f"{key}_seed_sd"] = float(r.seed_sd)
            out[f"{key}_seed_min"], out[f"{key}_seed_max"] = float(r.seed_min), float(r.seed_max)
    return out


def nan_cells(rows_: pd.DataFrame) -> list[str]:
    """The MLflow names of the cells over only some windows (over the minimum distance or rotation) that
    have no value: no window travelled or turned enough (evaluate's warning)."""
    out = []
    for r in rows_.itertuples(index=False):
        m = mt.get(r.metric)
        if m.windows != mt.ALL_WINDOWS and not np.isfinite(r.estimate):
            out.append(m.metric_key(r.split, r.horizon_s))
    return out


# -- what the readers make of the rows -----------------------------------------------------------------------
def runs(table: pd.DataFrame) -> pd.DataFrame:
    """One row per model run (the floor's rows left out): the key columns that name it and
    :data:`RUN_COLUMNS`, and ``horizons_scored``: the horizons it has a paper metric's value at; newest
    first. A run an evaluate took from an earlier one (benchmark/evaluate/reuse.py) has rows in the files of
    both: the row of a FINISHED evaluate is the run's (a run a killed evaluate finished is on a board only
    as the run of a complete evaluate that took it)."""
    t = table[table["role"] == MODEL]
    t = t.sort_values("evaluate_status", key=lambda s: s == "FINISHED", kind="stable")  # FINISHED last
    if not len(t):
        return pd.DataFrame(columns=["run_id", "evaluate_id", "model", "inputs", "terrain", *RUN_COLUMNS,
                                     "horizons_scored"])  # fmt: skip
    paper = {m.name for m in mt.PAPER}
    has = t[t["metric"].isin(paper) & t["estimate"].notna()]
    scored = has.groupby("run_id")["horizon_s"].agg(lambda h: sorted(set(h))).to_dict()
    cols = ["run_id", "evaluate_id", "model", "inputs", "terrain", *RUN_COLUMNS]
    out = t.drop_duplicates("run_id", keep="last")[cols].copy()
    out["horizons_scored"] = [scored.get(r, []) for r in out["run_id"]]
    return out.sort_values("start_time", ascending=False, kind="stable").reset_index(drop=True)


def board(table: pd.DataFrame, chosen: pd.DataFrame, horizon_s: float) -> pd.DataFrame:
    """compare's board of the runs ``chosen`` (:func:`runs` rows): one row per run, in their order, with
    model, inputs, terrain, status, reason, version, package, code digest and distribution, external, run_id,
    start_time, every metric
    of :data:`~skidbench.benchmark.scoring.metrics.METRICS` on CV and LD at ``horizon_s`` by its MLflow name
    (with its window count, interval and blocks, and its spread over seeds when there is one), and the fit and
    predict numbers."""
    df = pd.DataFrame({
        "model": chosen["model"].to_numpy(object), "inputs": chosen["inputs"].to_numpy(object),
        "terrain": chosen["terrain"].to_numpy(object), "status": chosen["status"].to_numpy(object),
        "reason": chosen["reason"].fillna("").to_numpy(object),
        "version": chosen["model_version"].fillna("").to_numpy(object),
        "package": chosen["package"].fillna("").to_numpy(object),
        "code_digest": chosen["code_digest"].fillna("").to_numpy(object),
        "code_distribution": chosen["code_distribution"].fillna("").to_numpy(object),
        "external": chosen["external"].fillna(False).astype(bool).to_numpy(),
        "run_id": chosen["run_id"].to_numpy(object), "start_time": chosen["start_time"].to_numpy(),
    })  # fmt: skip
    at = table[
        np.isclose(table["horizon_s"].to_numpy(float), horizon_s) & table["run_id"].isin(chosen["run_id"])
    ]
    at = at[(at["role"] == MODEL) & (at["stratum"] == ALL)]
    metrics = {r: mlflow_metrics(g) for r, g in at.groupby("run_id", sort=False)}
    logged = {k for m in metrics.values() for k in m}
    for metric in mt.METRICS:
        for split in ("cv", "ld"):
            keys = [metric.metric_key(split, horizon_s), metric.windows_key(split, horizon_s)]
            if metric.bootstrap is not None:
                keys += list(metric.interval_keys(split, horizon_s))
                seed_sd = f"{metric.metric_key(split, horizon_s)}_seed_sd"  # evaluate seeds=N > 1
                keys += [seed_sd] if seed_sd in logged else []
            for key in keys:
                if key is not None:
                    df[key] = [metrics.get(r, {}).get(key, np.nan) for r in df["run_id"]]
    for col in ("fit_loss", "fit_time_s", "predict_time_s"):
        df[col] = chosen[col].to_numpy(float)
    df.loc[df["status"] == "RUNNING", "reason"] = "still running (or killed)"
    return df


def _evaluates(table: pd.DataFrame, inputs: str | None = None) -> pd.DataFrame:
    """One row per evaluate (or score) parent run of the model rows (under ``inputs``): ``evaluate_id``,
    ``evaluate_status`` (its own rows': a score's rows hanging from an evaluate have a file of their own)
    and ``start_time`` (its newest own run's: an evaluate's file also holds the rows of the runs it took
    from earlier evaluates, benchmark/evaluate/reuse.py, with their older start times; a score's rows count
    only for an evaluate that has no other), newest first."""
    t = table[(table["role"] == MODEL) & (table["evaluate_id"].fillna("") != "")]
    if inputs:
        t = t[t["inputs"] == inputs]
    t = t.assign(_ext=t["external"].fillna(False).astype(bool)).sort_values("_ext", kind="stable")
    own = t[~t["_ext"] | ~t["evaluate_id"].isin(t.loc[~t["_ext"], "evaluate_id"])]
    out = own.groupby("evaluate_id", sort=False).agg(
        evaluate_status=("evaluate_status", "first"), start_time=("start_time", "max")
    )
    return out.reset_index().sort_values("start_time", ascending=False, kind="stable").reset_index(drop=True)


def latest_evaluate(table: pd.DataFrame, inputs: str | None = None) -> str | None:
    """The newest evaluate (or score) run of the table's model rows under ``inputs`` that FINISHED, else
    the newest of any status, else None."""
    ev = _evaluates(table, inputs)
    if not len(ev):
        return None
    done = ev[ev["evaluate_status"] == "FINISHED"]
    return str((done if len(done) else ev)["evaluate_id"].iloc[0])


#: an evaluate's settings every row of its board was scored with (the keys of :func:`settings_of`)
SETTING_KEYS = ("horizons", "splits", "min_distance_m", "min_rotation_deg", "models")


def settings_of(table: pd.DataFrame, evaluate_id: str) -> dict:
    """The settings an evaluate (or score) run scored with (:data:`SETTING_KEYS`), as its rows hold them
    (its own rows before those of a score hanging from it); {} when it has no row."""
    rows = table[table["evaluate_id"] == evaluate_id]
    if not len(rows):
        return {}
    own = rows[~rows["external"].fillna(False).astype(bool)]
    r = (own if len(own) else rows).iloc[0]
    return {"horizons": [float(h) for h in r["horizons"]], "splits": [str(s) for s in r["splits"]],
            "min_distance_m": float(r["min_distance_m"]), "min_rotation_deg": float(r["min_rotation_deg"]),
            "models": [str(m) for m in r["models"]]}  # fmt: skip
