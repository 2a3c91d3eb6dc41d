"""A public benchmark that keeps its answers (issues 35, 44), through the real CLI on the README quick start's
tiny dataset (session fixture ``readme_reproduce``, read only). docs/publishing.md's walkthroughs, run once
per session (fixture ``publishing_walkthrough``): the maintainer exported the public and private halves; a
lab imported the public half into ``lab-b``, wrote the ideal model's predictions (examples/predict_ideal.py,
without skidbench) and checked them; the maintainer imported both halves into ``board``, scored the
predictions with their identity, compared and published. Here: the public half holds no test truth (column
by column) and the oracle built from it fails for lack of targets; scoring without the private half is one
line; with it, the built-in models give the exported board cell for cell and the scored predictions equal
the ideal plugin's cells; a duplicate submission is one entry, km/h is refused naming the factor, bad files
are one line each; the page renders in headless Chromium at a laptop's width without sideways scrolling,
every entry linked, no local path in anything published."""

from __future__ import annotations

import datetime as dt
import json
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from browser import CHROMIUM, console_messages, page_value, run_chromium, text_of
from doc_blocks import doc_env
from reliability_data import in_process

from skidbench.benchmark.release.bundle import BundleError, verify
from skidbench.benchmark.release.halves import WINDOW_COLUMNS, WITHHELD_COLUMNS
from skidbench.benchmark.scoring import metrics as mt
from skidbench.pipeline.cli.overrides import check_overrides
from skidbench.pipeline.core.protocol import INPUT_COLUMNS
from skidbench.pipeline.core.schema import SPLIT_COLUMNS

pytestmark = pytest.mark.slow

DS = "sim-tiny"
MODELS = ("ideal", "edd", "full_linear", "roc", "enhanced", "friction", "drive_blr", "gp_residual")
#: the models the round trip re-evaluates (a parameter-free one, the paper's friction model with its batched
#: solver, a learned one with fitted arrays): the cost of the test; every built-in model was measured by hand
#: (docs/publishing.md, "Measured"; the walkthrough's test leaves its evaluate line out)
ROUND_TRIP = ("ideal", "friction", "gp_residual")
#: every metric evaluate logs at the 6 s horizon, and the window counts behind them (benchmark/scoring/)
CELLS = [
    k for m in mt.METRICS for s in ("cv", "ld") for k in (m.metric_key(s, 6.0), m.windows_key(s, 6.0)) if k
]
ENTRY = "ideal_dd"  # the walkthrough's submission
IDENTITY = ("score.link=https://example.org/x", "score.submitter=Lab C")


def skb(*args: str, out: Path, cwd: Path | None = None, ok: bool = True) -> subprocess.CompletedProcess:
    """``skidbench <args>`` with ``out`` as the output root (the environment of the docs' run blocks), run
    by the console script's ``main`` in this process (tests/reliability_data.py ``in_process``: the
    walkthrough's own commands run as processes; these runs' process is not what is tested)."""
    done = in_process(list(args), doc_env(out), cwd=cwd or out)
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
    """The folder of docs/publishing.md's walkthroughs, every command of which succeeded."""
    for r in publishing_walkthrough["results"]:
        assert r["returncode"] == 0, f"{r['cmd']} failed:\n{r['stderr'][-3000:]}"
    return Path(publishing_walkthrough["tmp"])


def walkthrough_stdout(publishing_walkthrough, start: str) -> str:
    """What the walkthrough's one command starting with ``start`` printed."""
    (out,) = [r["stdout"] for r in publishing_walkthrough["results"] if r["cmd"].startswith(start)]
    return out


@pytest.fixture(scope="module")
def public(walkthrough) -> Path:
    """The public half of the quick start's dataset: ``skidbench export sim-tiny release/``."""
    return walkthrough / "release" / "public"


@pytest.fixture(scope="module")
def private(walkthrough) -> Path:
    return walkthrough / "release" / "private"


@pytest.fixture(scope="module")
def board(walkthrough) -> Path:
    """The maintainer's output root: both halves imported, the walkthrough's submission scored, compared
    and published there, then the models of ``ROUND_TRIP`` evaluated (the walkthrough leaves its evaluate
    line out)."""
    out = walkthrough / "board"
    skb(
        "evaluate",
        "source=bundle",
        f"dataset={DS}",
        f"models=[{','.join(ROUND_TRIP)}]",
        "log_figures=false",
        out=out,
    )
    return out


def _rows(out: Path, protocol: str = "commanded") -> pd.DataFrame:
    from skidbench.benchmark.board import boards as brd
    from skidbench.benchmark.board.selection import results_of
    from skidbench.pipeline.core.layout import Layout
    from skidbench.pipeline.datasets.identity import read_record

    layout = Layout(out, DS)
    table = results_of(layout, read_record(layout)["fingerprint"], f"skidbench-{DS}")
    return brd.protocol_board(table, protocol).rows


def _sequences(doc: dict, splits: tuple[str, ...]) -> list[dict]:
    return [s for s in doc["sequences"] if s["split"] in splits]


# -- the halves ------------------------------------------------------------------------------------------
def test_the_public_half_holds_train_inputs_windows_and_the_private_half_the_answers(
    public, private, quickstart
):
    doc = json.loads((public / "bundle.json").read_text())
    assert (
        doc["format"] == "skidbench-bundle" and doc["release"] == "withheld" and doc["dataset"]["name"] == DS
    )
    assert doc["licence"] and doc["provenance"]["statement"] and doc["robot"]["name"] == "jackal"
    assert doc["protocol"]["boards"] == ["commanded", "response"]  # what make reproduce evaluated
    assert {"commanded", "response", "measured"} == set(doc["protocol"]["inputs"])  # the sim has encoders
    for s in _sequences(doc, ("train",)):  # Train byte for byte, with its ground truth
        assert (public / s["file"]).read_bytes() == (quickstart / DS / s["file"]).read_bytes()
    tests = _sequences(doc, ("cv", "ld"))
    assert tests and all(s["file"] is None for s in tests)
    assert not list(public.glob("splits/*/cv/*")) and not list(public.glob("splits/*/ld/*"))
    for protocol, terrains in doc["protocol"]["inputs"].items():  # every sequence's inputs, every protocol
        assert terrains == doc["dataset"]["terrains"]
        for s in doc["sequences"]:
            x = pd.read_parquet(
                public / "inputs" / protocol / s["terrain"] / s["split"] / f"{s['name']}.parquet"
            )
            assert list(x.columns) == list(INPUT_COLUMNS) and len(x) == s["rows"]
    answers = json.loads((private / "answers.json").read_text())
    assert {a["name"] for a in answers["sequences"]} == {s["name"] for s in tests}
    for a in answers["sequences"]:  # the answers byte for byte
        assert (private / a["file"]).read_bytes() == (quickstart / DS / a["file"]).read_bytes()
    for half in (public, private):  # every file listed with its sha256, as sha256sum reads it
        sums = verify(half, "bundle.json" if half == public else "answers.json")
        assert len(sums) == len([p for p in half.rglob("*") if p.is_file()]) - 1
        if shutil.which("sha256sum"):
            subprocess.run(["sha256sum", "--quiet", "-c", "SHA256SUMS"], cwd=half, check=True)
    board = json.loads((public / "board" / "commanded.json").read_text())["rows"]
    assert {(r["model"], r["terrain"]) for r in board} == {
        (m, t) for m in MODELS for t in doc["dataset"]["terrains"]
    }


def test_no_column_of_the_public_half_recovers_a_test_pose_or_velocity(public, private):
    """Every table of the public half, column by column, against the split schema's ground truth of every CV
    and LD sequence: no column of the truth by name, none equal to a truth column (or the speed) in value."""
    truth = {}
    for p in private.glob("splits/*/*/*.parquet"):
        df = pd.read_parquet(p)
        truth[p.stem] = {k: df[k].to_numpy(float) for k in WITHHELD_COLUMNS} | {
            "speed": np.hypot(df["vx"], df["vy"]).to_numpy(float)
        }
    assert set(WITHHELD_COLUMNS) <= set(SPLIT_COLUMNS) and len(truth) == 6
    checked = 0
    for path in public.rglob("*.parquet"):
        cols = pq.read_schema(path).names
        table = pd.read_parquet(path)
        seqs = table["sequence"].astype(str).unique() if "sequence" in table else [path.stem]
        for seq in (s for s in seqs if s in truth):
            rows = table[table["sequence"].astype(str) == seq] if "sequence" in table else table
            assert not set(cols) & set(WITHHELD_COLUMNS), (
                f"{path}: {sorted(set(cols) & set(WITHHELD_COLUMNS))}"
            )
            for c in cols:
                v = pd.to_numeric(rows[c], errors="coerce").to_numpy(float)
                for k, y in truth[seq].items():
                    same = len(v) == len(y) and np.std(y) > 1e-6 and np.allclose(v, y, rtol=1e-3, atol=1e-6)
                    assert not same, f"{path}: column {c} of {seq} equals its ground truth's {k}"
                checked += 1
    assert checked >= 6 * len(INPUT_COLUMNS) * 3  # the inputs of three protocols for every test sequence
    assert pq.read_schema(public / "windows.parquet").names == list(WINDOW_COLUMNS)


def test_the_oracle_built_from_the_public_half_fails_for_lack_of_targets(public):
    """The predictions file the issue's oracle wrote (the test splits' own vx, vy, wz, copied): from the
    public half alone there is nothing to copy it from."""
    doc = json.loads((public / "bundle.json").read_text())
    tests = {s["name"] for s in _sequences(doc, ("cv", "ld"))}
    frames = []
    for path in public.rglob("*.parquet"):
        names = pq.read_schema(path).names
        if {"vx", "vy", "wz"} <= set(names):
            df = pd.read_parquet(path)
            seq = str(pq.read_metadata(path).metadata.get(b"sequence", path.stem.encode()).decode())
            if seq in tests:
                frames.append(df.assign(sequence=seq)[["sequence", "t", "vx", "vy", "wz"]])
    assert frames == []  # no target of a test sequence anywhere


def test_score_without_the_private_half_is_refused_and_check_validates_the_file(
    walkthrough, publishing_walkthrough
):
    lab = walkthrough / "lab-b"
    pred = walkthrough / "predictions.parquet"
    line = one_line_error(skb("score", DS, "--predictions", str(pred), *IDENTITY, out=lab, ok=False), "score")
    assert "public half" in line and "withheld" in line and "score.check=true" in line
    line = one_line_error(skb("evaluate", "source=bundle", f"dataset={DS}", out=lab, ok=False), "evaluate")
    assert "withheld" in line
    check = walkthrough_stdout(
        publishing_walkthrough, "skidbench score sim-tiny --predictions predictions.parquet score.check=true"
    )
    assert "a valid predictions file" in check and "nothing scored" in check and "6 test sequences" in check
    bad = walkthrough / "kmh.parquet"
    df = pd.read_parquet(pred)
    df[["vx", "vy"]] *= 3.6
    df.to_parquet(bad)
    line = one_line_error(
        skb("score", DS, "--predictions", str(bad), "score.check=true", out=lab, ok=False), "score"
    )
    assert re.search(r"predicted speed \d\.\d+ times the fastest the commands could produce", line), line
    assert "km/h instead of m/s" in line


def test_import_refuses_a_changed_file_or_the_answers_of_another_public_half(public, private, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(public, copy)
    target = next(iter(sorted(copy.glob("splits/*/train/*.parquet"))))
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
    shutil.copyfile(public / target.relative_to(copy), target)
    (copy / "README.md").write_text("another public half\n")  # and its checksums again: a valid other half
    from skidbench.benchmark.release.bundle import write_sums

    write_sums(copy)
    line = one_line_error(skb("import", str(copy), f"bundle.answers={private}", out=out, ok=False), "import")
    assert "answers.json" in line and "another public half" in line


# -- the maintainer's board --------------------------------------------------------------------------------
def test_the_answers_evaluated_again_give_the_exported_board_cell_for_cell(public, board):
    from skidbench.benchmark.board import boards as brd

    exported = brd.read_board(public / "board" / "commanded.json").rows
    again = _rows(board)
    cells = [c for c in CELLS if c in exported]
    assert len(cells) >= 12  # RMSRE, end-position RMSE and their windows on CV and LD, at least
    key = ["model", "terrain"]
    a = exported[exported["model"].isin(ROUND_TRIP)].set_index(key).sort_index()
    b = again[~again["external"].astype(bool)].set_index(key).sort_index()  # the submission aside
    assert list(a.index) == list(b.index) and len(a) == len(ROUND_TRIP) * 3
    assert (a["status"] == "FINISHED").all() and (b["status"] == "FINISHED").all()
    for c in cells:
        x, y = a[c].to_numpy(float), b[c].to_numpy(float)
        same = (x == y) | (np.isnan(x) & np.isnan(y))
        assert same.all(), f"{c}: {list(a.index[~same])}: exported {x[~same]} vs again {y[~same]}"
    assert set(b["splits_fingerprint"]) == set(a["splits_fingerprint"])  # the same split files


def test_the_submission_equals_the_ideal_plugin_cell_for_cell_with_its_identity(
    board, walkthrough, publishing_walkthrough
):
    out = walkthrough_stdout(
        publishing_walkthrough, "skidbench score sim-tiny --predictions predictions.parquet score.name="
    )
    assert f"score: {ENTRY} (external" in out and "submitted by Lab B on" in out
    rows = _rows(board)
    ext = rows[rows["model"] == ENTRY].set_index("terrain").sort_index()
    plugin = rows[rows["model"] == "ideal"].set_index("terrain").sort_index()
    assert len(ext) == 3 and ext["external"].all() and not plugin["external"].any()
    sha = subprocess.run(
        ["sha256sum", str(walkthrough / "predictions.parquet")], capture_output=True, text=True
    ).stdout.split()[0]
    assert set(ext["predictions_sha256"]) == {sha} and set(ext["model_version"]) == {"external"}
    assert set(ext["submitter"]) == {"Lab B"} and set(ext["link"]) == {"https://example.org/ideal-dd"}
    assert set(ext["submitted"]) == {dt.datetime.now(dt.UTC).date().isoformat()}
    cells = [c for c in CELLS if c in rows and plugin[c].notna().all()]  # the ideal model has no covariance
    assert len(cells) >= 12
    for c in cells:
        assert ext[c].to_numpy(float).tolist() == plugin[c].to_numpy(float).tolist(), c
    # before the built-in models were evaluated there, the walkthrough's board had this one entry
    compared = walkthrough_stdout(publishing_walkthrough, "skidbench compare source=bundle")
    assert ENTRY in compared and "no entry ranked: the only entry" in compared


def test_the_same_predictions_are_one_entry_and_names_are_strings(board, walkthrough):
    pred = walkthrough / "predictions.parquet"
    before = _rows(board)
    line = one_line_error(
        skb("score", DS, "--predictions", str(pred), "score.name=other", *IDENTITY, out=board, ok=False),
        "score",
    )
    assert f"already on the inputs=commanded board as {ENTRY!r}" in line
    again = skb("score", DS, "--predictions", str(pred), f"score.name={ENTRY}", *IDENTITY, out=board)
    assert "already this entry" in again.stdout and "nothing logged" in again.stdout
    assert _rows(board)["run_id"].tolist() == before["run_id"].tolist()
    df = pd.read_parquet(pred)
    df["vx"] *= 0.98  # other predictions
    other = walkthrough / "nan.parquet"
    df.to_parquet(other)
    line = one_line_error(
        skb("score", DS, "--predictions", str(other), f"score.name={ENTRY}", *IDENTITY, out=board, ok=False),
        "score",
    )
    assert f"score.name={ENTRY}: already the inputs=commanded entry of other predictions" in line
    line = one_line_error(
        skb("score", DS, "--predictions", str(other), "score.name=nan", out=board, ok=False), "score"
    )
    assert "score.link is not set" in line
    done = skb("score", DS, "--predictions", str(other), "score.name=nan", *IDENTITY, out=board)
    assert "score: nan (external" in done.stdout  # the text as given, not a float
    assert "nan" in set(_rows(board)["model"])


@pytest.mark.parametrize(
    ("damage", "expected"),
    [
        ("drop_sequence", r"no rows for sequence (\w+) \(\w+ (CV|LD)\)"),
        ("nan", r"sequence \w+: 1 NaN or infinite value\(s\) in vy \(first at t="),
        ("shift", r"sequence \w+: times shifted by \+0\.0333\d* s against its split"),
    ],
)
def test_a_bad_predictions_file_is_one_line_naming_the_sequence(
    board, walkthrough, tmp_path, damage, expected
):
    df = pd.read_parquet(walkthrough / "predictions.parquet")
    seq = sorted(df["sequence"].unique())[0]
    if damage == "drop_sequence":
        df = df[df["sequence"] != seq]
    elif damage == "nan":
        df.loc[df.index[df["sequence"] == seq][5], "vy"] = np.nan
    else:
        df.loc[df["sequence"] == seq, "t"] += 1 / 30
    bad = tmp_path / f"{damage}.csv"
    df.to_csv(bad, index=False)
    line = one_line_error(
        skb("score", DS, "--predictions", str(bad), *IDENTITY, out=board, ok=False), "score"
    )
    assert str(bad) in line and re.search(expected, line), line
    assert seq in line


def test_import_prints_next_steps_that_run_as_printed(walkthrough, publishing_walkthrough):
    """Each ``next:`` line of the walkthrough's two imports, its placeholders filled: the overrides check
    as the CLI checks them, and the cheap ones run (evaluate is the round trip's, above)."""
    fill = {
        "<file>": str(walkthrough / "next.parquet"),
        "<url>": "https://example.org/next",
        "<who>": "'Lab N'",
    }
    df = pd.read_parquet(walkthrough / "predictions.parquet")
    df["wz"] *= 0.97
    df.to_parquet(fill["<file>"])
    for start in ("skidbench import release/public out_root=lab-b", "skidbench import release/public bundle"):
        printed = walkthrough_stdout(publishing_walkthrough, start)
        lines = [ln.strip() for ln in printed.split("next:", 1)[1].splitlines() if ln.strip()]
        assert lines and all("out_root=" in ln for ln in lines), printed
        for ln in lines:
            for k, v in fill.items():
                ln = ln.replace(k, v)
            argv = shlex.split(ln)
            assert argv[0] == "skidbench"
            if argv[1] == "evaluate":
                check_overrides("evaluate", argv[2:])
                continue
            done = in_process(argv[1:], doc_env(walkthrough), cwd=walkthrough)
            assert done.returncode == 0, f"{ln}\n{done.stderr[-2000:]}"


# -- the page ---------------------------------------------------------------------------------------------
#: after every entry's details are opened: the page's width against the window's, and its entries' links
OPENED = """(() => {
  if (!document.documentElement.getAttribute('data-rendered-ms')) return null;
  document.querySelectorAll('button.more').forEach((b) => b.click());
  const rows = [...document.querySelectorAll('tr.entry')];
  return JSON.stringify({scroll: document.documentElement.scrollWidth, width: innerWidth,
    opened: document.querySelectorAll('tr.more-row:not([hidden])').length, entries: rows.length,
    links: rows.map((r) => [r.dataset.model, (r.querySelector('a[href]') || {}).getAttribute?.call(
      r.querySelector('a[href]'), 'href') || null]),
    ids: [...document.querySelectorAll('[id]')].map((e) => e.id)});
})()"""


def _no_local_path(folder: Path, *paths: Path) -> None:
    """No file under ``folder`` names any of ``paths`` (or the home, the checkout, a temporary folder)."""
    words = {str(p) for p in paths} | {str(Path.home()), str(Path(__file__).resolve().parents[1]), "/tmp/"}
    for f in folder.rglob("*"):
        if f.is_file():
            text = f.read_text(errors="replace")
            for w in words:
                assert w not in text, f"{f}: names {w}"


@pytest.mark.skipif(CHROMIUM is None, reason="no headless Chromium (/usr/bin/chromium) installed")
def test_the_published_page_fits_a_laptop_links_every_entry_and_shows_the_leaderboard(quickstart, tmp_path):
    site = tmp_path / "site"
    done = skb("publish", DS, str(site), out=quickstart)
    page = site / DS / "index.html"
    assert "publish:" in done.stdout and page.is_file() and (site / "index.html").is_file()
    text = page.read_text()
    assert "<title>Jackal on asphalt, grass and tile (simulated)</title>" in text  # from the card
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", text)  # nothing fetched from elsewhere
    _no_local_path(site, quickstart, tmp_path)
    run = run_chromium(page.as_uri(), tmp_path, console=True, budget_ms=5000, window="1366,768")
    assert console_messages(run.stderr) == []
    dom = run.stdout
    words = text_of(dom)
    for heading in (
        "Inputs commanded",
        "The dataset",
        "Built-in methods",
        "Submit a method",
        "Fig. 3",
        "Fig. 7",
        "Reproduce this page",
        "withheld",
    ):
        assert heading in words, heading
    geo = json.loads(page_value(page.as_uri(), tmp_path, OPENED, window="1366,768"))
    assert geo["scroll"] <= geo["width"] == 1366, geo  # no sideways scrolling, every entry opened
    assert (
        geo["opened"] == geo["entries"] - 2 == 2 * len(MODELS)
    )  # every entry but the floor of each protocol
    for model, href in geo["links"]:
        if model != "floor":
            assert href and href.startswith("#method-") and href[1:] in geo["ids"], (model, href)
    # every number of compare's leaderboard file of each protocol is the page's, in its entry's details
    for protocol, end in (("commanded", 'id="response"'), ("response", 'id="dataset"')):
        lb = pd.read_csv(quickstart / DS / "reports" / f"leaderboard-{protocol}.csv")
        section = dom[dom.index(f'id="{protocol}"') : dom.index(end)]
        n = 0
        for r in lb.to_dict("records"):
            m = re.search(rf'<tr data-model="{r["model"]}" data-terrain="{r["terrain"]}">(.*?)</tr>', section)
            assert m, (protocol, r["model"], r["terrain"])
            values = [float(v) for v in re.findall(r'data-value="([^"]+)"', m.group(1))]
            for col in ("trans CV %", "trans LD %", "rot CV %", "rot LD %"):
                assert float(r[col]) in values, (protocol, r["model"], r["terrain"], col)
                n += 1
        assert n == 4 * len(lb) == 4 * 3 * len(MODELS)
    assert page.stat().st_size < 5e6


def test_the_walkthroughs_page_shows_the_submission_with_its_identity(walkthrough):
    site = walkthrough / "site"
    text = (site / DS / "index.html").read_text()
    m = re.search(rf'<tr class="entry" id="commanded-{ENTRY}"[^>]*>(.*?)</tr>', text)
    assert m, "no entry row"
    row = m.group(1)
    assert 'href="https://example.org/ideal-dd"' in row and "Lab B" in row
    assert dt.datetime.now(dt.UTC).date().isoformat() in row
    assert "the ideal differential drive: no slip" in text  # its description, in its details
    # what the intervals cover (the quick start's data: one drive per terrain and split)
    assert re.search(r"class='note scope'>Intervals: [^<]*within this drive[^<]*not how another drive", text)
    assert 'href="https://example.org/public-half.tar"' in text  # where to get the public half
    assert "withheld" in text_of(text)
    _no_local_path(site, walkthrough)
