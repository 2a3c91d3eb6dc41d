"""The MLflow UI as a user sees it, in a real headless Chromium: a `mlflow server` on a store this test
writes (an evaluate and a compare), the page `compare` links (the experiment's runs with the saved view)
and a parent run's page. Skipped, with the reason, where no Chromium is installed.

``SKIDBENCH_UI_SCREENSHOT=<file.png>`` also saves a screenshot of the runs page (the README's)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
from _bench_data import compose, fit_fn, write_splits
from browser import CHROMIUM, chromium, text_of
from mlflow_server import running_mlflow_server

from skidbench.benchmark.compare import run_compare
from skidbench.benchmark.evaluate import run_benchmark

DS = "sim-mini"
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(CHROMIUM is None, reason="no headless Chromium (/usr/bin/chromium) installed"),
]
RMSRE = ("ld_6s_trans_rmsre_pct", "ld_6s_rot_rmsre_pct", "cv_6s_trans_rmsre_pct", "cv_6s_rot_rmsre_pct")


@pytest.fixture(scope="module")
def ui(tmp_path_factory):
    root = tmp_path_factory.mktemp("ui")
    mp = pytest.MonkeyPatch()
    (root / "server").mkdir()
    with running_mlflow_server(root / "server") as uri:
        mp.setenv("MLFLOW_TRACKING_URI", uri)
        write_splits(root / DS, counts={"train": 1, "cv": 1, "ld": 1}, duration_s=20.0)
        res = run_benchmark(
            compose("evaluate", root, ["models=[chi,ideal_t]"]), fit_fn=fit_fn, log_figures=False
        )
        out = run_compare(compose("compare", root, ["figures.enabled=false"]))
        yield root, res, out.links
    mp.undo()


def test_the_linked_runs_page_shows_the_rmsre_columns_and_the_child_runs(ui):
    root, res, links = ui
    url = links["runs table (saved view)"]
    assert url.startswith(os.environ.get("MLFLOW_TRACKING_URI", "http://127.0.0.1"))
    dom = chromium(url, root)
    text = text_of(dom)
    assert "Runs" in text and "Overview" not in text  # the runs table, not the GenAI overview of traces
    for m in RMSRE:  # the benchmark's columns, displayed (ag-grid renders a header cell per shown column)
        assert f'col-id="metrics.`{m}`"' in dom, m
        assert m in text, m
    for child in ("chi/tile", "chi/grass", "ideal_t/tile", "ideal_t/grass"):
        assert child in text, child
    # the best model of each terrain comes first: rows sorted by LD translational RMSRE, grouped by terrain
    assert text.index("chi/tile") < text.index("ideal_t/tile")
    assert text.index("chi/grass") < text.index("ideal_t/grass")
    if os.environ.get("SKIDBENCH_UI_SCREENSHOT"):
        shot = Path(os.environ["SKIDBENCH_UI_SCREENSHOT"]).absolute()
        chromium(url, root, screenshot=shot)
        assert shot.stat().st_size > 10000


def test_a_parent_runs_page_shows_its_name_description_and_datasets(ui):
    root, res, links = ui
    text = text_of(chromium(links["parent run"], root))
    assert f"evaluate {DS} commanded 20" in text  # its unique, searchable name
    assert "Benchmark of 2 models on 2 terrains" in text  # its description
    assert re.search(rf"Datasets {DS}/(grass|tile)/(train|cv|ld) ", text)  # its dataset inputs
    assert re.search(r"Child runs .*chi/tile", text)
    assert "Created by" in text and "Source" in text and "Created by -" not in text
