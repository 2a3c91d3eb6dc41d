"""What the MLflow UI opens on: the links ``compare`` prints and the saved views of the runs table.

MLflow 3.17's UI opens an experiment (and every page under it) in its GenAI mode unless the link says
``workflowType=machine_learning`` (or the browser remembers the user's toggle), and shows only the Source,
Models and Dataset columns of a runs table until a user picks more; a *saved view* (an experiment tag
``mlflow.sharedViewState.<key>``, opened by ``?viewStateShareKey=<key>``, listed in the UI's "Views"
menu) is the UI's own way to ship columns, sort, grouping and charts. So every link here carries
``workflowType=machine_learning``, and the runs of an evaluate are shown through a saved view: its child
runs grouped by terrain, the RMSRE columns right after the run name, best model first; in chart mode
(``compareRunsMode=CHART``) one bar chart per RMSRE column, every run shown.

Saved views of an evaluate: ``evaluate-<run id[:8]>`` (that evaluate, for ever) and
``latest-<protocol>-<user>`` (a user's latest evaluate under an input protocol: another protocol or
another person's evaluate never replaces it).
"""

from __future__ import annotations

import json
import time
import urllib.parse
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.tracking.tags import TAG_PARENT, TAG_TERRAIN, current_user

TAG_SAVED_VIEW = "mlflow.sharedViewState."  # + key: a saved view of the UI's runs table (experiment tag)
#: what `make mlflow-ui` serves; links printed for a local (SQLite) store point there
DEFAULT_UI_URL = "http://127.0.0.1:5000"
ML_MODE = {"workflowType": "machine_learning"}  # the UI's model-training pages, not its GenAI ones


def ui_url(uri: str, ui: str | None = None) -> str:
    """The MLflow UI that shows the store ``uri``: a tracking server's own URL, else ``ui`` (what
    ``make mlflow-ui`` serves by default)."""
    if uri.startswith(("http://", "https://")):
        return uri.rstrip("/")
    return (ui or DEFAULT_UI_URL).rstrip("/")


def run_url(uri: str, experiment_id: str, run_id: str, ui: str | None = None) -> str:
    """A run's page (its description, metrics, child runs, artifacts)."""
    q = urllib.parse.urlencode(ML_MODE)
    return f"{ui_url(uri, ui)}/#/experiments/{experiment_id}/runs/{run_id}?{q}"


def experiment_url(uri: str, experiment_id: str, ui: str | None = None) -> str:
    """An experiment's runs page in the UI's model-training mode (the bare experiment link opens its GenAI
    overview)."""
    return f"{ui_url(uri, ui)}/#/experiments/{experiment_id}/runs?{urllib.parse.urlencode(ML_MODE)}"


def view_url(uri: str, experiment_id: str, key: str, ui: str | None = None, charts: bool = False) -> str:
    """The runs page of the saved view ``key``: its table, or (``charts``) its charts."""
    q = {"viewStateShareKey": key, **ML_MODE, **({"compareRunsMode": "CHART"} if charts else {})}
    return f"{ui_url(uri, ui)}/#/experiments/{experiment_id}/runs?{urllib.parse.urlencode(q)}"


def latest_key(protocol: str, user: str | None = None) -> str:
    """The saved view of a user's latest evaluate under ``protocol``: ``latest-commanded-alice``."""
    return f"latest-{protocol}-{_key_part(user or current_user())}"


def _key_part(text: str) -> str:
    return "".join(c if c.isalnum() or c in "_." else "_" for c in text)


def board_columns(splits: Sequence[str], horizon_s: float) -> tuple[list[str], list[str]]:
    """The headline metrics at ``horizon_s`` (:mod:`~skidbench.benchmark.scoring.metrics`) and their labels,
    the
    paper's first, LD before CV (LD trans, LD rot, CV trans, CV rot, then the others): the columns of an
    evaluate's saved views and of its parent run's leaderboard."""
    order = sorted(splits, key=lambda s: s != "ld")
    pairs = [(m, s) for s in order for m in mt.PAPER]
    pairs += [(m, s) for s in order for m in mt.HEADLINE if m not in mt.PAPER]
    return [m.metric_key(s, horizon_s) for m, s in pairs], [m.column_label(s) for m, s in pairs]


def children_of(parent_id: str) -> str:
    """The search filter of a parent run's child runs."""
    return f"tags.`{TAG_PARENT}` = '{parent_id}'"


def view_state(search_filter: str, columns: Sequence[str], order_by: str, chart_title: str) -> dict[str, Any]:
    """The runs table's state (MLflow 3.17's names): the runs ``search_filter`` finds (the child runs of an
    evaluate: :func:`children_of`) grouped by terrain (a group's row: the best, i.e. smallest, value), the
    metric ``columns`` right after the run name and its start time (the UI pins both left), wide enough for
    their names (all four RMSRE columns fit a 1920 px wide window, next to the UI's assistant panel too,
    no scrolling), then the logged models; rows sorted by ``order_by`` ascending (the best model of each
    terrain first); in
    chart mode one bar chart per column (section ``chart_title``) over every run (not the UI's first 10,
    nor the groups' minima), before any chart the UI adds itself."""
    metrics = [f"metrics.`{c}`" for c in columns]
    section = "skidbench-errors"
    return {
        "searchFilter": search_filter,
        "orderByKey": f"metrics.`{order_by}`",
        "orderByAsc": True,
        "selectedColumns": [*metrics, "attributes.`Models`"],
        "columnOrder": [
            "attributes.`Run Name`",
            *metrics,
            "attributes.`Models`",
            "runDateAndNestInfo",
            "duration",
        ],  # fmt: skip
        "columnWidths": {m: 8 * len(c) + 24 for m, c in zip(metrics, columns, strict=True)},
        "runsHiddenMode": "SHOW_ALL",
        "useGroupedValuesInCharts": False,
        "groupBy": {"aggregateFunction": "min", "groupByKeys": [{"mode": "tag", "groupByData": TAG_TERRAIN}]},
        "compareRunSections": [{"uuid": section, "name": chart_title, "display": True, "isReordered": False}],
        "compareRunCharts": [
            {
                "uuid": f"skidbench-{c}",
                "type": "BAR",
                "deleted": False,
                "isGenerated": False,
                "metricSectionId": section,
                "metricKey": c,
                "dataAccessKey": c,
                "displayName": c,
            }
            for c in columns
        ],  # fmt: skip
        "isAccordionReordered": True,
    }


def save_view(client: Any, experiment_id: str, key: str, title: str, state: dict[str, Any]) -> None:
    """Save ``state`` (:func:`view_state`) as the view ``key`` of the experiment, titled ``title``."""
    now = int(time.time() * 1000)
    envelope = {"name": title, "createdAt": now, "updatedAt": now, "state": json.dumps(state)}
    client.set_experiment_tag(experiment_id, TAG_SAVED_VIEW + key, json.dumps(envelope))


def chart_title(horizon_s: float) -> str:
    return f"{horizon_s:g} s errors, lower is better"


def save_evaluate_views(
    client: Any, experiment_id: str, parent_id: str, title: str, columns: Sequence[str], protocol: str,
    horizon_s: float, taken: Sequence[str] = (),
) -> list[str]:  # fmt: skip
    """The saved views of an evaluate: ``evaluate-<id[:8]>`` and this user's ``latest-<protocol>-<user>``,
    its child runs and the runs it ``taken`` unchanged from earlier evaluates, with the RMSRE ``columns``
    (the first one sorts). Returns their keys."""
    search = children_of(parent_id)
    if taken:  # its own runs and the ones it took: one list of run ids (a search has no OR)
        own = client.search_runs([experiment_id], search, max_results=10000)
        ids = ", ".join(f"'{r}'" for r in [*(r.info.run_id for r in own), *taken])
        search = f"attributes.run_id IN ({ids})"
    state = view_state(search, columns, columns[0], chart_title(horizon_s))
    keys = [f"evaluate-{parent_id[:8]}", latest_key(protocol)]
    save_view(client, experiment_id, keys[0], title, state)
    save_view(client, experiment_id, keys[1], f"latest {protocol} ({current_user()}): {title}", state)
    return keys


def print_ui_links(uri: str, ui: str = DEFAULT_UI_URL) -> None:
    """For ``make mlflow-ui``: per skidbench experiment of the store, the runs page to open: this user's
    latest evaluate under each input protocol (its saved view), else the experiment's runs page."""
    from mlflow.tracking import MlflowClient

    from skidbench.benchmark.tracking.store import has_store, quiet_mlflow_logs

    quiet_mlflow_logs()
    if not has_store(uri):
        print(f"no MLflow store at {uri} yet: run `make reproduce` (or `skidbench evaluate`) first")
        return
    for exp in MlflowClient(uri).search_experiments(filter_string="name LIKE 'skidbench-%'"):
        me = f"-{_key_part(current_user())}"
        mine = sorted(k.removeprefix(TAG_SAVED_VIEW) for k in exp.tags
                      if k.startswith(TAG_SAVED_VIEW + "latest-") and k.endswith(me))  # fmt: skip
        for key in mine:
            print(f"{exp.name} ({key}): {view_url(uri, exp.experiment_id, key, ui)}")
        if not mine:
            print(f"{exp.name}: {experiment_url(uri, exp.experiment_id, ui)}")


# -- the parent run's page: the leaderboard -------------------------------------------------------------
def metric_safe(name: str) -> str:
    """``name`` with the characters MLflow refuses in a metric key (an augmented spec's ``+``) as ``_``."""
    return "".join(c if c.isalnum() or c in "_-. /:" else "_" for c in name)


def leaderboard(
    rows: Sequence[tuple[str, str, str, Mapping[str, float]]], columns: Sequence[str], labels: Sequence[str]
) -> tuple[str, dict[str, float]]:
    """The leaderboard an evaluate's parent run shows, from its child runs ``rows`` = (model, terrain,
    status, metrics): per model the mean over the terrains it FINISHED of each metric of ``columns`` (lower
    is better; ``labels`` their headers), in order of the first: point estimates, not a ranking (evaluate has
    no paired intervals; ``skidbench compare`` ranks by the rule of docs/intervals.md). Returns its
    Markdown (for the run's description) and the parent's metrics ``<model>.mean_<column>`` and
    ``<model>.gap_to_next_<column>`` (how far ahead of the next model on that column, in its unit; none
    for the last)."""
    models = list(dict.fromkeys(r[0] for r in rows))
    means: dict[str, dict[str, float]] = {}
    ok: dict[str, tuple[int, int]] = {}
    for m in models:
        mine = [r for r in rows if r[0] == m]
        done = [r[3] for r in mine if r[2] == "FINISHED"]
        ok[m] = (len(done), len(mine))
        means[m] = {}
        for c in columns:
            vals = np.array([d.get(c, np.nan) for d in done], float)
            means[m][c] = float(np.nanmean(vals)) if np.isfinite(vals).any() else float("nan")
    metrics: dict[str, float] = {}
    gaps: dict[str, dict[str, float]] = {m: {} for m in models}
    for c in columns:
        ranked = sorted((m for m in models if np.isfinite(means[m][c])), key=lambda m: means[m][c])
        for a, b in zip(ranked, ranked[1:], strict=False):
            gaps[a][c] = round(means[b][c] - means[a][c], 3)
        for m in ranked:
            metrics[f"{metric_safe(m)}.mean_{c}"] = round(means[m][c], 3)
            if c in gaps[m]:
                metrics[f"{metric_safe(m)}.gap_to_next_{c}"] = gaps[m][c]
    first = columns[0]
    order = sorted(models, key=lambda m: (not np.isfinite(means[m][first]), means[m][first]))
    cell = lambda v: "n/a" if not np.isfinite(v) else f"{v:.2f}"  # noqa: E731
    head = ["order", "model", *labels, f"gap to next ({labels[0]})", "terrains"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---:|---|" + "---:|" * (len(labels) + 1) + "---|"]
    for k, m in enumerate(order, 1):
        gap = gaps[m].get(first)
        cells = [str(k), m, *(cell(means[m][c]) for c in columns),
                 "" if gap is None else f"{gap:.2f}", f"{ok[m][0]}/{ok[m][1]}"]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines), metrics


def evaluate_leaderboard(
    rows: Sequence[tuple[str, str, str, Mapping[str, float]]], splits: Sequence[str], horizon_s: float,
    protocol: str,
) -> tuple[str, dict[str, float]]:  # fmt: skip
    """An evaluate's :func:`leaderboard` over :func:`board_columns`: the Markdown that opens its parent
    run's description (with a title line) and the parent's per-model metrics."""
    cols, labels = board_columns(splits, horizon_s)
    md, metrics = leaderboard(rows, cols, labels)
    title = (f"**Leaderboard**, inputs={protocol}, {horizon_s:g} s horizon: mean over terrains, lower is "
             "better, in order of the first column's point estimate, not a ranking: each child run logs its "
             "95 % intervals (`_ci_lo`, `_ci_hi`), and `skidbench compare` ranks on paired intervals (a gap "
             "inside them is a tie)")  # fmt: skip
    return f"{title}\n\n{md}\n\n", metrics
