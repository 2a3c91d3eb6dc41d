"""The example plugins pip-installed into a FRESH virtual environment work exactly like the built-ins: the
model examples (examples/skidbench-ridge, -slipgrid) are listed by `skidbench models` and fitted by
`skidbench fit model=...`; the source example (examples/skidbench-rostopic-csv) is extracted by `skidbench
extract source=rostopic_csv`. One environment holds the three (built once for this module).

The fresh venv (``--without-pip``; this project's pip installs into it with ``pip --python``) sees this
project's installed packages through a .pth file that runs
``site.addsitedir(<project venv site-packages>)`` (so nothing is downloaded for skidbench's dependencies);
the plugin itself is installed with ``pip install --no-deps`` (without build isolation when ``wheel`` is
importable, else with it, which fetches setuptools/wheel from the configured index)."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from skidbench.models.fitting.synthetic import write_train_splits

REPO = Path(__file__).resolve().parents[1]
PLUGIN = REPO / "examples" / "skidbench-ridge"

pytestmark = pytest.mark.slow


def run(cmd, **kw):
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300, **kw)
    assert p.returncode == 0, f"{cmd}\n{p.stdout}\n{p.stderr}"
    return p


SLIPGRID = REPO / "examples" / "skidbench-slipgrid"
CSV_SOURCE = REPO / "examples" / "skidbench-rostopic-csv"


@pytest.fixture(scope="module")
def venv_python(tmp_path_factory) -> Path:
    """A fresh venv with the three examples installed (one pip call): its python."""
    venv = tmp_path_factory.mktemp("plugins") / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", str(venv)])  # the project's pip installs into it
    py = venv / "bin" / "python"
    site_dir = run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]
    ).stdout.strip()
    parent = sysconfig.get_paths()["purelib"]  # this interpreter's (the project venv's) site-packages
    Path(site_dir, "_skidbench_parent.pth").write_text(f"import site; site.addsitedir({parent!r})\n")
    isolation = ["--no-build-isolation"] if importlib.util.find_spec("wheel") else []
    pip = [str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check", "--no-deps", *isolation]
    run([*pip, str(PLUGIN), str(SLIPGRID), str(CSV_SOURCE)])
    return py


def test_example_plugin_installs_into_a_fresh_venv_and_fits_like_a_builtin(tmp_path, jackal, venv_python):
    py = venv_python
    env = {**os.environ, "SKIDBENCH_OUT": str(tmp_path / "out")}
    cli = [str(py), "-m", "skidbench.pipeline.cli.main"]
    listing = run([*cli, "models"], env=env).stdout
    rows = {line.split()[0]: line for line in listing.splitlines()[1:]}
    assert "skidbench-ridge" in rows["ridge"] and "friction" in rows

    write_train_splits(tmp_path / "out", jackal, terrains=("tile",))
    run(
        [*cli, "fit", "model=ridge", "terrain=tile", "track=false", "calibrate.use=false"],
        env=env,
        cwd=tmp_path,
    )
    fit = tmp_path / "out" / "sim-mini" / "fits" / "ridge" / "tile.json"
    import json

    saved = json.loads(fit.read_text())
    assert saved["model"] == "ridge" and saved["package"] == "skidbench-ridge"
    assert saved["options"]["alpha"] == pytest.approx(1e-3)  # from the plugin's own conf/model/ridge.yaml
    assert saved["fit_loss"] < 1e-3

    # not installed in the project's own environment: the built-ins do not depend on it
    listed = subprocess.run(
        [sys.executable, "-m", "skidbench.pipeline.cli.main", "models"], capture_output=True, text=True
    ).stdout
    assert not re.search(r"^\s*ridge\b", listed, re.M), listed


def test_example_learned_plugin_installs_into_a_fresh_venv_and_saves_its_arrays(
    tmp_path, jackal, venv_python
):
    """The learned example (fitted arrays, predictive covariance) works from a fresh venv: listed, fitted
    by the fit stage with its arrays in ``<terrain>.arrays.npz``, reloaded and predicting with variance."""
    py = venv_python
    env = {**os.environ, "SKIDBENCH_OUT": str(tmp_path / "out")}
    cli = [str(py), "-m", "skidbench.pipeline.cli.main"]
    listing = run([*cli, "models"], env=env).stdout
    assert "skidbench-slipgrid" in {line.split()[0]: line for line in listing.splitlines()[1:]}["slipgrid"]

    write_train_splits(tmp_path / "out", jackal, terrains=("tile",))
    run(
        [*cli, "fit", "model=slipgrid", "terrain=tile", "track=false", "calibrate.use=false"],
        env=env,
        cwd=tmp_path,
    )
    fits = tmp_path / "out" / "sim-mini" / "fits" / "slipgrid"
    import json

    saved = json.loads((fits / "tile.json").read_text())
    assert saved["package"] == "skidbench-slipgrid" and saved["arrays"]["file"] == "tile.arrays.npz"
    assert {"mean", "var", "v_edges", "w_edges"} <= set(saved["arrays"]["names"])
    check = (
        "import numpy as np; from pathlib import Path; from omegaconf import OmegaConf;"
        "from skidbench.models.fitting.fit import FitSettings, load_fitted;"
        "from skidbench.models.fitting.synthetic import command_table;"
        f"cfg = OmegaConf.create({{'out_root': {str(tmp_path / 'out')!r}, 'dataset': 'sim-mini',"
        "'robot': OmegaConf.load(__import__('importlib.resources').resources.files('skidbench.conf')"
        ".joinpath('robot/jackal.yaml')), 'calibrate': {'use': False}});"
        "m = load_fitted(FitSettings.from_cfg(cfg), 'slipgrid', 'tile'); tab = command_table(m.robot, 50);"
        "c = m.predict_cov(tab); assert m.predict(tab).shape == (50, 3) and c.shape == (50, 3, 3);"
        "assert np.all(c[:, [0, 1, 2], [0, 1, 2]] > 0); print('ok')"
    )
    assert run([str(py), "-c", check], env=env, cwd=tmp_path).stdout.strip() == "ok"


def _rostopic_logs(root: Path) -> dict[str, dict]:
    """Two tiny recordings as `rostopic echo -p` writes them (Twist + Odometry; TwistStamped +
    PoseStamped), 40 rows at 20 Hz; returns what each should extract to."""
    import numpy as np
    import pandas as pd

    t = 1_700_000_000_000_000_001 + np.arange(40) * 50_000_000  # 19 digits: exact only as integers
    yaw = 0.02 * np.arange(40)
    quat = {"x": 0.0, "y": 0.0, "z": np.sin(yaw / 2), "w": np.cos(yaw / 2)}
    out = {}
    for name, cat, twist, pose in [("run_a", "train", "field", "field.pose.pose"),
                                   ("run_b", "cv", "field.twist", "field.pose")]:  # fmt: skip
        folder = root / "tile" / cat / name
        folder.mkdir(parents=True)
        v, w = (0.5, 0.2) if name == "run_a" else (0.3, -0.1)
        cmd = {"%time": t, f"{twist}.linear.x": v, f"{twist}.linear.y": 0.0, f"{twist}.linear.z": 0.0,
               f"{twist}.angular.x": 0.0, f"{twist}.angular.y": 0.0, f"{twist}.angular.z": w}  # fmt: skip
        if twist != "field":
            cmd = {"%time": t, "field.header.seq": np.arange(40), "field.header.stamp": t, **cmd}
        pd.DataFrame(cmd).to_csv(folder / "cmd_vel.csv", index=False)
        x = 0.025 * np.arange(40)
        poses = {f"{pose}.position.{k}": val for k, val in {"x": x, "y": 0.0, "z": 0.0}.items()}
        poses |= {f"{pose}.orientation.{k}": val for k, val in quat.items()}
        pd.DataFrame({"%time": t, "field.header.frame_id": "odom", **poses}).to_csv(folder / "odom.csv",
                                                                                   index=False)  # fmt: skip
        out[name] = {"category": cat, "t": t, "v": v, "w": w, "x": x, "yaw": yaw}
    return out


def test_example_source_installs_into_a_fresh_venv_and_extracts_like_a_builtin(tmp_path, venv_python):
    """`skidbench extract source=rostopic_csv` from a fresh venv: the plugin's config and entry point are
    found, its tables written under the contract's names with exact stamps and the pose's yaw; an unknown
    source kind is one line naming the installed ones, the plugin's among them."""
    import json

    import numpy as np
    import pandas as pd

    logs = tmp_path / "logs"
    expected = _rostopic_logs(logs)
    env = {**os.environ, "SKIDBENCH_OUT": str(tmp_path / "out")}
    cli = [str(venv_python), "-m", "skidbench.pipeline.cli.main", "extract", "source=rostopic_csv"]
    run([*cli, f"source.root={logs}", "source.dataset=csvlogs"], env=env, cwd=tmp_path)

    ds = tmp_path / "out" / "csvlogs"
    manifest = json.loads((ds / "raw" / "manifest.json").read_text())
    assert {s["name"]: s["category"] for s in manifest["sequences"]} == {"run_a": "train", "run_b": "cv"}
    assert manifest["format"] == "rostopic_csv"
    for name, want in expected.items():
        cmd = pd.read_parquet(ds / "extracted" / name / "cmd_vel.parquet")
        gt = pd.read_parquet(ds / "extracted" / name / "gt_pose.parquet")
        assert cmd["stamp_ns"].tolist() == want["t"].tolist() == gt["stamp_ns"].tolist()
        assert np.all(cmd["linear_x"] == want["v"]) and np.all(cmd["angular_z"] == want["w"])
        np.testing.assert_allclose(gt["x"], want["x"])
        np.testing.assert_allclose(gt["yaw"], want["yaw"], atol=1e-12)
        info = json.loads((ds / "extracted" / name / "_extract.json").read_text())
        assert info["source"] == "rostopic_csv" and info["tables"] == {"cmd_vel": 40, "gt_pose": 40}

    p = subprocess.run([*cli, f"source.root={logs}", "source.dataset=csvlogs", "source.kind=rostopic_cvs"],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)  # fmt: skip
    assert p.returncode == 2, p.stderr
    line = p.stderr.strip().splitlines()[-1]
    assert "source.kind='rostopic_cvs': no such source installed" in line
    assert "(installed: amrl_txt, bag, drive_df, rostopic_csv)" in line


def _tame_package(folder: Path) -> Path:
    """A model plugin package (distribution skidbench-tame, model ``tame``: the ideal model under another
    name), as a lab member would write it from docs/plugins.md."""
    pkg = folder / "skidbench-tame"
    (pkg / "skidbench_tame").mkdir(parents=True)
    (pkg / "skidbench_tame" / "__init__.py").write_text(
        "from skidbench.models.kinematic.ideal import IdealDifferentialDrive\n\n\n"
        "class Tame(IdealDifferentialDrive):\n"
        "    name = 'tame'\n"
        "    version = '0.1'\n"
    )
    (pkg / "pyproject.toml").write_text(
        '[build-system]\nrequires = ["setuptools>=61"]\nbuild-backend = "setuptools.build_meta"\n\n'
        '[project]\nname = "skidbench-tame"\nversion = "0.1"\n\n'
        '[project.entry-points."skidbench.models"]\ntame = "skidbench_tame:Tame"\n\n'
        '[tool.setuptools]\npackages = ["skidbench_tame"]\n'
    )
    return pkg


def test_an_edited_plugin_is_refitted_and_rescored_alone_and_an_uninstalled_one_is_shown_not_ranked(
    tmp_path, venv_python
):
    """A plugin installed (not editable) in a fresh venv, evaluated beside a built-in; one line of its
    installed code edited, version not bumped: the next evaluate says so in one line, fits and scores that
    model alone and takes the built-in's run unchanged; after `pip uninstall`, compare exits 0, keeps its
    row visible as "code not installed here" and does not rank it."""
    import pandas as pd
    from _bench_data import write_splits
    from mlflow import MlflowClient

    py = venv_python
    isolation = ["--no-build-isolation"] if importlib.util.find_spec("wheel") else []
    pip = [str(py), "-m", "pip", "-q", "--disable-pip-version-check"]
    run([*pip, "install", "--no-deps", *isolation, str(_tame_package(tmp_path))])
    out = tmp_path / "out"
    write_splits(out / "sim-mini", terrains=("tile",), counts={"train": 1, "cv": 1, "ld": 1}, duration_s=16.0)
    env = {**os.environ, "SKIDBENCH_OUT": str(out)}
    env.pop("MLFLOW_TRACKING_URI", None)
    cli = [str(py), "-m", "skidbench.pipeline.cli.main"]
    evaluate = [
        *cli,
        "evaluate",
        "models=[ideal,tame]",
        "calibrate.use=false",
        "log_figures=false",
        "horizons=[6.0]",
    ]
    run(evaluate, env=env, cwd=tmp_path)
    fits = out / "sim-mini" / "fits"
    ideal_fit = (fits / "ideal" / "tile.json").stat().st_mtime_ns

    installed = run([str(py), "-c", "import skidbench_tame; print(skidbench_tame.__file__)"]).stdout.strip()
    assert "site-packages" in installed  # the installed copy, not the source folder
    with open(installed, "a") as f:
        f.write("# an edit, version not bumped\n")
    again = run(evaluate, env=env, cwd=tmp_path).stdout
    (line,) = [x for x in again.splitlines() if x.startswith("evaluate: tame: ")]
    assert "its code changed (digest " in line and "run again on 1 terrain(s)" in line
    assert "taken as they are: ideal/tile" in again and "evaluate: ideal:" not in again
    assert (fits / "ideal" / "tile.json").stat().st_mtime_ns == ideal_fit  # not refitted
    client = MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    (exp,) = [e for e in client.search_experiments() if e.name != "Default"]
    runs = sorted(client.search_runs([exp.experiment_id]), key=lambda r: r.info.start_time)
    parents = [r for r in runs if r.data.tags["skidbench.role"] == "parent"]
    first, second = (
        {
            r.data.tags["skidbench.model"]: r
            for r in runs
            if r.data.tags.get("mlflow.parentRunId") == p.info.run_id
        }
        for p in parents
    )
    assert sorted(second) == ["tame"]  # the model whose code changed, alone
    assert (
        second["tame"].data.tags["skidbench.code.digest"] != first["tame"].data.tags["skidbench.code.digest"]
    )
    assert parents[1].data.tags["skidbench.reused_runs"] == first["ideal"].info.run_id
    assert [m.value for m in client.get_metric_history(second["tame"].info.run_id, "fit_loss")] == [
        second["tame"].data.metrics["fit_loss"]
    ]  # logged once

    run([*pip, "uninstall", "-y", "skidbench-tame"])
    compare = [*cli, "compare", "figures.enabled=false"]
    res = subprocess.run(compare, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "tame/tile: code not installed here (model tame is not installed)" in res.stdout
    board = pd.read_csv(out / "sim-mini" / "reports" / "leaderboard-commanded.csv", dtype=str)
    tame = board[board["model"].str.startswith("tame")]
    assert len(tame) == 1 and tame["status"].iloc[0] == "FINISHED"  # kept, with its numbers
    (line,) = [x for x in res.stdout.splitlines() if "| tame (code not installed here) |" in x]
    assert "not ranked: code not installed here (model tame is not installed)" in line
    ideal = next(x for x in res.stdout.splitlines() if "| ideal |" in x)  # the ranked board comes first
    assert "code not installed" not in ideal
