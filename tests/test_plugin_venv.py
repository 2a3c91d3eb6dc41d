"""The example plugin (examples/skidbench-ridge) pip-installed into a FRESH virtual environment is listed by
`skidbench models` and fitted by `skidbench fit model=ridge terrain=...`, exactly like a built-in.

The fresh venv (``--without-pip``; this project's pip installs into it with ``pip --python``) sees this
project's installed packages through a .pth file that runs
``site.addsitedir(<project venv site-packages>)`` (so nothing is downloaded for skidbench's dependencies);
the plugin itself is installed with ``pip install --no-deps`` (without build isolation when ``wheel`` is
importable, else with it, which fetches setuptools/wheel from the configured index)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from skidbench.models.synthetic import write_train_splits

REPO = Path(__file__).resolve().parents[1]
PLUGIN = REPO / "examples" / "skidbench-ridge"

pytestmark = pytest.mark.slow


def run(cmd, **kw):
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300, **kw)
    assert p.returncode == 0, f"{cmd}\n{p.stdout}\n{p.stderr}"
    return p


def test_example_plugin_installs_into_a_fresh_venv_and_fits_like_a_builtin(tmp_path, jackal):
    venv = tmp_path / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", str(venv)])  # the project's pip installs into it
    py = venv / "bin" / "python"
    site_dir = run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]
    ).stdout.strip()
    parent = sysconfig.get_paths()["purelib"]  # this interpreter's (the project venv's) site-packages
    Path(site_dir, "_skidbench_parent.pth").write_text(f"import site; site.addsitedir({parent!r})\n")
    isolation = ["--no-build-isolation"] if importlib.util.find_spec("wheel") else []
    run(
        [
            str(py),
            "-m",
            "pip",
            "install",
            "-q",
            "--disable-pip-version-check",
            "--no-deps",
            *isolation,
            str(PLUGIN),
        ]
    )

    env = {**os.environ, "SKIDBENCH_OUT": str(tmp_path / "out")}
    cli = [str(py), "-m", "skidbench.pipeline.cli"]
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
    assert (
        "ridge"
        not in subprocess.run(
            [sys.executable, "-m", "skidbench.pipeline.cli", "models"], capture_output=True, text=True
        ).stdout
    )


SLIPGRID = REPO / "examples" / "skidbench-slipgrid"


def test_example_learned_plugin_installs_into_a_fresh_venv_and_saves_its_arrays(tmp_path, jackal):
    """The learned example (fitted arrays, predictive covariance) works from a fresh venv: listed, fitted
    by the fit stage with its arrays in ``<terrain>.arrays.npz``, reloaded and predicting with variance."""
    venv = tmp_path / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", str(venv)])
    py = venv / "bin" / "python"
    site_dir = run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]
    ).stdout.strip()
    parent = sysconfig.get_paths()["purelib"]
    Path(site_dir, "_skidbench_parent.pth").write_text(f"import site; site.addsitedir({parent!r})\n")
    isolation = ["--no-build-isolation"] if importlib.util.find_spec("wheel") else []
    pip = [str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check", "--no-deps", *isolation]
    run([*pip, str(SLIPGRID)])

    env = {**os.environ, "SKIDBENCH_OUT": str(tmp_path / "out")}
    cli = [str(py), "-m", "skidbench.pipeline.cli"]
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
        "from skidbench.models.fitting import load_fitted;"
        "from skidbench.models.synthetic import command_table;"
        f"cfg = OmegaConf.create({{'out_root': {str(tmp_path / 'out')!r}, 'dataset': 'sim-mini',"
        "'robot': OmegaConf.load(__import__('importlib.resources').resources.files('skidbench.conf')"
        ".joinpath('robot/jackal.yaml')), 'calibrate': {'use': False}});"
        "m = load_fitted(cfg, 'slipgrid', 'tile'); tab = command_table(m.robot, 50);"
        "c = m.predict_cov(tab); assert m.predict(tab).shape == (50, 3) and c.shape == (50, 3, 3);"
        "assert np.all(c[:, [0, 1, 2], [0, 1, 2]] > 0); print('ok')"
    )
    assert run([str(py), "-c", check], env=env, cwd=tmp_path).stdout.strip() == "ok"
