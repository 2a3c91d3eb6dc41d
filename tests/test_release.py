"""A released benchmark (issue 35), through the real CLI on the README quick start's tiny dataset (session
fixture ``readme_reproduce``, read only). docs/publishing.md's walkthrough, run once per session (fixture
``publishing_walkthrough``), exported it, imported the bundle into a fresh output root, scored the ideal
model's predictions there (written by examples/predict_ideal.py, without skidbench), compared and
published: here the bundle holds what it should, a corrupted copy is refused, the built-in models evaluated
again in the imported dataset give the exported board cell for cell, the scored predictions equal the ideal
plugin's cells and bad predictions files are one line each; ``skidbench publish`` renders in headless
Chromium with no console message and the numbers of the leaderboard files."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from browser import CHROMIUM, console_messages, run_chromium, text_of
from doc_blocks import doc_env

from skidbench.benchmark.release.bundle import BundleError, verify
from skidbench.benchmark.scoring import metrics as mt
from skidbench.pipeline.core.protocol import INPUT_COLUMNS, TARGET_COLUMNS

pytestmark = pytest.mark.slow

DS = "sim-tiny"
MODELS = ("ideal", "edd", "full_linear", "roc", "enhanced", "friction", "drive_blr", "gp_residual")
#: the models the round trip re-evaluates (a parameter-free one, the paper's friction model with its batched
#: solver, a learned one with fitted arrays): the cost of the test; every built-in model was measured by hand
#: (docs/publishing.md, "Measured"; the walkthrough's test leaves its evaluate line out)
ROUND_TRIP = ("ideal", "friction", "gp_residual")
#: every metric evaluate logs at the 6 s horizon, and the window counts behind them
# (benchmark/scoring/metrics.py)
CELLS = [
    k for m in mt.METRICS for s in ("cv", "ld") for k in (m.metric_key(s, 6.0), m.windows_key(s, 6.0)) if k
]
SKB = str(Path(sys.executable).parent / "skidbench")


def skb(*args: str, out: Path, cwd: Path | None = None, ok: bool = True) -> subprocess.CompletedProcess:
    """``skidbench <args>`` with ``out`` as the output root (the environment of the docs' run blocks)."""
    done = subprocess.run([SKB, *args], env=doc_env(out), cwd=cwd or out, capture_output=True, text=True,
                          timeout=1800)  # fmt: skip
    if ok:
        assert done.returncode == 0, f"skidbench {' '.join(args)}:\n{done.stderr[-3000:]}"
    return done


def one_line_error(done: subprocess.CompletedProcess, stage: str) -> str:
    """The one line a refused command printed on stderr (exit status 2)."""
    assert done.returncode == 2, done.stderr[-2000:]
    lines = [ln for ln in done.stderr.splitlines() if ln.startswith(f"skidbench {stage}: error:")]
    assert len(lines) == 1, done.stderr[-2000:]
    return lines[0]


@pytest.fixture(scope="module")
def quickstart(readme_reproduce) -> Path:
    for r in readme_reproduce["results"]:
        assert r["returncode"] == 0, f"{r['cmd']} failed:\n{r['stderr'][-3000:]}"
    return Path(readme_reproduce["root"])


@pytest.fixture(scope="module")
def walkthrough(publishing_walkthrough) -> Path:
    """The folder of docs/publishing.md's walkthrough, every command of which succeeded."""
    for r in publishing_walkthrough["results"]:
        assert r["returncode"] == 0, f"{r['cmd']} failed:\n{r['stderr'][-3000:]}"
    return Path(publishing_walkthrough["tmp"])


def walkthrough_stdout(publishing_walkthrough, stage: str) -> str:
    """What the walkthrough's ``skidbench <stage>`` printed."""
    (out,) = [
        r["stdout"] for r in publishing_walkthrough["results"] if r["cmd"].startswith(f"skidbench {stage} ")
    ]
    return out


@pytest.fixture(scope="module")
def bundle(walkthrough) -> Path:
    """The quick start's dataset exported (inputs=commanded): ``skidbench export sim-tiny release/``."""
    return walkthrough / "release"


@pytest.fixture(scope="module")
def imported(walkthrough, publishing_walkthrough) -> Path:
    """The bundle imported into a fresh output root (the walkthrough's ``lab-b``, where it also scored the
    ideal model's predictions) and the models of ``ROUND_TRIP`` evaluated there (here: the walkthrough
    leaves its evaluate line out)."""
    out = walkthrough / "lab-b"
    assert f"skidbench evaluate source=bundle dataset={DS}" in walkthrough_stdout(
        publishing_walkthrough, "import"
    )
    skb("evaluate", "source=bundle", f"dataset={DS}", f"models=[{','.join(ROUND_TRIP)}]", "log_figures=false",
        out=out)  # fmt: skip
    return out


def test_the_bundle_holds_the_splits_calibration_boards_inputs_and_checksums(bundle, quickstart):
    doc = json.loads((bundle / "bundle.json").read_text())
    assert doc["format"] == "skidbench-bundle" and doc["dataset"]["name"] == DS
    assert doc["licence"] and doc["provenance"]["statement"] and doc["robot"]["name"] == "jackal"
    assert doc["protocol"]["version"] >= 1 and doc["metric"]["version"] >= 1
    assert doc["protocol"]["boards"] == ["commanded", "response"]  # what make reproduce evaluated
    # the split files byte for byte
    for s in doc["sequences"]:
        assert (bundle / s["file"]).read_bytes() == (quickstart / DS / s["file"]).read_bytes()
    for t in doc["dataset"]["terrains"]:
        cal = json.loads((bundle / "calibration" / f"{t}.json").read_text())
        assert "wheel_response" in cal and "wheel_radius" in cal
    # every file listed with its sha256, as sha256sum reads it
    sums = verify(bundle)
    assert "bundle.json" in sums and len(sums) == len([p for p in bundle.rglob("*") if p.is_file()]) - 1
    if shutil.which("sha256sum"):
        subprocess.run(["sha256sum", "--quiet", "-c", "SHA256SUMS"], cwd=bundle, check=True)
    # the model inputs: the protocol's columns only, the split's commands as they are (commanded)
    for s in doc["sequences"]:
        x = pd.read_parquet(bundle / "inputs" / "commanded" / Path(s["file"]).relative_to("splits"))
        assert list(x.columns) == list(INPUT_COLUMNS) and not set(TARGET_COLUMNS) & set(x.columns)
        split = pd.read_parquet(bundle / s["file"])
        assert np.array_equal(x["cmd_wl"].to_numpy(), split["cmd_wl"].to_numpy())
        assert (x["sequence"] == s["name"]).all()
    # the board: every row with its provenance
    board = json.loads((bundle / "board" / "commanded.json").read_text())
    rows = board["rows"]
    assert {(r["model"], r["terrain"]) for r in rows} == {
        (m, t) for m in MODELS for t in doc["dataset"]["terrains"]
    }
    for r in rows:
        assert r["run_id"] and r["git_commit"] and r["dataset_id"] and r["splits_fingerprint"]
        assert f"models=[{r['model']}]" in r["reproduce"] and r["external"] is False


def test_import_refuses_a_changed_missing_or_unlisted_file_in_one_line(bundle, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(bundle, copy)
    target = next(iter(sorted(copy.glob("splits/*/cv/*.parquet"))))
    data = bytearray(target.read_bytes())
    data[len(data) // 2] ^= 0xFF
    target.write_bytes(bytes(data))
    out = tmp_path / "out"
    out.mkdir()
    line = one_line_error(skb("import", str(copy), out=out, ok=False), "import")
    assert str(target) in line and "sha256" in line
    assert not any(out.iterdir()) or [p.name for p in out.iterdir()] == ["hydra"]  # no dataset made
    target.unlink()
    with pytest.raises(BundleError, match=re.escape(f"{target}: listed in SHA256SUMS but missing")):
        verify(copy)
    shutil.copyfile(bundle / target.relative_to(copy), target)
    (copy / "extra.txt").write_text("x")
    with pytest.raises(BundleError, match="extra.txt: not listed in SHA256SUMS"):
        verify(copy)


def test_the_imported_bundle_evaluated_again_gives_the_exported_board_cell_for_cell(bundle, imported):
    from skidbench.benchmark.board import boards as brd
    from skidbench.benchmark.tracking.store import Tracker
    from skidbench.pipeline.core.layout import Layout
    from skidbench.pipeline.datasets.identity import read_record

    exported = brd.read_board(bundle / "board" / "commanded.json").rows
    layout = Layout(imported, DS)
    tracker = Tracker(layout.mlflow_uri, f"skidbench-{DS}", dataset_id=read_record(layout)["fingerprint"])
    again = brd.protocol_board(tracker, "commanded").rows
    cells = [c for c in CELLS if c in exported]
    assert len(cells) >= 12  # RMSRE, end-position RMSE and their windows on CV and LD, at least
    key = ["model", "terrain"]
    a = exported[exported["model"].isin(ROUND_TRIP)].set_index(key).sort_index()
    b = again[~again["external"].astype(bool)].set_index(key).sort_index()  # the scored file's rows aside
    assert list(a.index) == list(b.index) and len(a) == len(ROUND_TRIP) * 3
    assert (a["status"] == "FINISHED").all() and (b["status"] == "FINISHED").all()
    for c in cells:
        x, y = a[c].to_numpy(float), b[c].to_numpy(float)
        same = (x == y) | (np.isnan(x) & np.isnan(y))
        assert same.all(), f"{c}: {list(a.index[~same])}: exported {x[~same]} vs again {y[~same]}"
    assert set(b["splits_fingerprint"]) == set(a["splits_fingerprint"])  # the same split files


def test_an_imported_dataset_refuses_its_frozen_stages_and_another_robot(imported):
    line = one_line_error(skb("split", "source=bundle", f"dataset={DS}", out=imported, ok=False), "split")
    assert "imported from a bundle" in line and "frozen" in line
    line = one_line_error(skb("evaluate", "source=bundle", f"dataset={DS}", "robot=husky", out=imported,
                              ok=False), "evaluate")  # fmt: skip
    assert "set robot=jackal" in line


@pytest.fixture(scope="module")
def ideal_predictions(walkthrough) -> Path:
    """The ideal model's predictions, written from the bundle by examples/predict_ideal.py (no skidbench)."""
    return walkthrough / "predictions.parquet"


def test_scored_predictions_of_the_ideal_model_equal_its_plugin_cell_for_cell(
    imported, ideal_predictions, publishing_walkthrough
):
    from skidbench.benchmark.board import boards as brd
    from skidbench.benchmark.tracking.store import Tracker
    from skidbench.pipeline.core.layout import Layout
    from skidbench.pipeline.datasets.identity import read_record

    name = ideal_predictions.stem  # score's default name of a predictions file
    assert f"{name} (external" in walkthrough_stdout(publishing_walkthrough, "score")
    layout = Layout(imported, DS)
    tracker = Tracker(layout.mlflow_uri, f"skidbench-{DS}", dataset_id=read_record(layout)["fingerprint"])
    rows = brd.protocol_board(tracker, "commanded").rows  # compare's rows: the external one is on the board
    ext = rows[rows["model"] == name].set_index("terrain").sort_index()
    plugin = rows[rows["model"] == "ideal"].set_index("terrain").sort_index()
    assert len(ext) == 3 and ext["external"].all() and not plugin["external"].any()
    sha = subprocess.run(
        ["sha256sum", str(ideal_predictions)], capture_output=True, text=True
    ).stdout.split()[0]
    assert set(ext["predictions_sha256"]) == {sha} and set(ext["version"]) == {"external"}
    cells = [c for c in CELLS if c in rows and plugin[c].notna().all()]  # the ideal model has no covariance
    assert len(cells) >= 12
    for c in cells:
        assert ext[c].to_numpy(float).tolist() == plugin[c].to_numpy(float).tolist(), c
    assert name in walkthrough_stdout(publishing_walkthrough, "compare")  # the walkthrough's compare lists it
    # compare ranks it with the others
    done = skb("compare", "source=bundle", f"dataset={DS}", "figures.enabled=false", out=imported)
    assert name in done.stdout and "friction" in done.stdout


@pytest.mark.parametrize(
    ("damage", "expected"),
    [
        ("drop_sequence", r"no rows for sequence (\w+) \(\w+ (CV|LD)\)"),
        ("nan", r"sequence \w+: 1 NaN or infinite value\(s\) in vy \(first at t="),
        ("shift", r"sequence \w+: times shifted by \+0\.0333\d* s against its split"),
    ],
)
def test_a_bad_predictions_file_is_one_line_naming_the_sequence(imported, ideal_predictions, tmp_path, damage,
                                                                 expected):  # fmt: skip
    df = pd.read_parquet(ideal_predictions)
    seq = sorted(df["sequence"].unique())[0]
    if damage == "drop_sequence":
        df = df[df["sequence"] != seq]
    elif damage == "nan":
        df.loc[df.index[df["sequence"] == seq][5], "vy"] = np.nan
    else:
        df.loc[df["sequence"] == seq, "t"] += 1 / 30
    bad = tmp_path / f"{damage}.csv"
    df.to_csv(bad, index=False)
    line = one_line_error(skb("score", DS, "--predictions", str(bad), out=imported, ok=False), "score")
    assert str(bad) in line and re.search(expected, line), line
    assert seq in line


@pytest.mark.skipif(CHROMIUM is None, reason="no headless Chromium (/usr/bin/chromium) installed")
def test_the_published_page_renders_without_console_messages_with_the_leaderboard_numbers(
    quickstart, tmp_path
):
    site = tmp_path / "site"
    done = skb("publish", DS, str(site), out=quickstart)
    page = site / DS / "index.html"
    assert "publish:" in done.stdout and page.is_file() and (site / "index.html").is_file()
    text = page.read_text()
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", text)  # nothing fetched from elsewhere
    run = run_chromium(page.as_uri(), tmp_path, console=True, budget_ms=5000)
    assert console_messages(run.stderr) == []
    dom = run.stdout
    assert re.search(r'data-rendered-ms="\d+"', dom)  # its script ran to the end
    words = text_of(dom)
    for heading in ("Leaderboard", "Per terrain and test split", "Provenance of each row", "Dataset card",
                    "Fig. 3", "Fig. 7", "Reproduce this page"):  # fmt: skip
        assert heading in words, heading
    # every number of compare's leaderboard file of each protocol is the page's, in that protocol's section
    for protocol, end in (("commanded", 'id="response"'), ("response", 'id="figures"')):
        lb = pd.read_csv(quickstart / DS / "reports" / f"leaderboard-{protocol}.csv")
        section = dom[dom.index(f'id="{protocol}"') : dom.index(end)]
        n = 0
        for r in lb.to_dict("records"):
            m = re.search(rf'<tr[^>]*data-model="{r["model"]}" data-terrain="{r["terrain"]}"[^>]*>(.*?)</tr>',
                          section)  # fmt: skip
            assert m, (protocol, r["model"], r["terrain"])
            values = [float(v) for v in re.findall(r'data-value="([^"]+)"', m.group(1))]
            for col in ("trans CV %", "trans LD %", "rot CV %", "rot LD %"):
                assert float(r[col]) in values, (protocol, r["model"], r["terrain"], col)
                assert f">{float(r[col]):.2f}<" in m.group(1)
                n += 1
        assert n == 4 * len(lb) == 4 * 3 * len(MODELS)
    assert page.stat().st_size < 5e6
