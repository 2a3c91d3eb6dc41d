"""An unknown or misspelt override is one line naming the key and the nearest valid ones, exit status 2,
for every stage; sweeps, ``+key`` additions and ``hydra.*`` settings still pass."""

from __future__ import annotations

import subprocess
import sys

import pytest

from skidbench.pipeline.cli import main as cli
from skidbench.pipeline.cli.overrides import check_overrides
from skidbench.pipeline.core.errors import ConfigError

# (stage, overrides, the whole message after "skidbench <stage>: error: ")
MISSPELT = [
    ("groundtruth", ["groundtruth.method=orbslam", "groundtruth.orbslam.dri=/x"],
     "unknown config key 'groundtruth.orbslam.dri'; did you mean 'groundtruth.orbslam.dir'?"),
    ("extract", ["source=bag", "source.rooot=/x"],
     "unknown config key 'source.rooot'; did you mean 'source.root'?"),
    ("fit", ["modle=edd", "terrain=tile"], "unknown config key 'modle'; did you mean 'model'?"),
    ("extract", ["source.topics.cmd_vel.topc=/x"],
     "unknown config key 'source.topics.cmd_vel.topc'; did you mean 'source.topics.cmd_vel.topic'?"),
    ("split", ["split.alow_flagged=true"],
     "unknown config key 'split.alow_flagged'; did you mean 'split.allow_flagged'?"),
    ("fit", ["model=edf"], "unknown option 'model=edf'; did you mean 'model=edd'? "
     "(options of 'model': drive_blr, edd, enhanced, friction, full_linear, gp_residual, ideal, relax, roc, "
     "state_ridge)"),
    ("fit", ["-m", "model=edd,fricton", "terrain=tile,grass"], "unknown option 'model=fricton'; did you mean "
     "'model=friction'? (options of 'model': drive_blr, edd, enhanced, friction, full_linear, gp_residual, "
     "ideal, relax, roc, state_ridge)"),
    ("fit", ["hydra/launcher=joblib", "hydra.launcher.n_jbs=4"],
     "unknown config key 'hydra.launcher.n_jbs'; did you mean 'hydra.launcher.n_jobs'?"),
    ("fit", ["-m", "model=edd,ideal", "terain=tile,grass"],
     "unknown config key 'terain'; did you mean 'terrain'?"),
    ("simulate", ["sclae=tiny"], "unknown config key 'sclae'; did you mean 'scale'?"),
]  # fmt: skip


@pytest.mark.parametrize(("stage", "overrides", "message"), MISSPELT, ids=[" ".join(c[1]) for c in MISSPELT])
def test_a_misspelt_override_is_one_line_naming_the_nearest_key(capsys, stage, overrides, message):
    with pytest.raises(SystemExit) as exit_:
        cli.main([stage, *overrides])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [f"skidbench {stage}: error: {message}"], err


def test_a_key_like_no_other_lists_the_valid_keys_where_it_was_meant():
    with pytest.raises(ConfigError) as exc:
        check_overrides("evaluate", ["zzz=1", "source=bag", "source.topics.imu.zzz=2"])
    assert str(exc.value).startswith("unknown config key 'zzz'; valid keys at the top level: ")
    assert ", dataset, " in str(exc.value) and ", models, " in str(exc.value)
    assert "hydra" not in str(exc.value)
    with pytest.raises(ConfigError) as exc:
        check_overrides("evaluate", ["source.topics.imu.qqqqqq=2"])
    assert str(exc.value) == (
        "unknown config key 'source.topics.imu.qqqqqq'; "
        "valid keys under 'source.topics.imu': required, topic, type"
    )


@pytest.mark.parametrize(
    "overrides",
    [
        [
            "-m",
            "model=edd,friction,roc",
            "terrain=tile,grass",
            "hydra/launcher=joblib",
            "hydra.launcher.n_jobs=2",
        ],
        ["+extra.note=hello", "++seed=3", "model=ideal"],
        ["-m", "model=glob(*)", "terrain=tile"],
        ["--cfg", "job", "model=edd"],
        ["--help"],
    ],
    ids=["sweep", "additions", "glob sweep", "cfg job", "help"],
)
def test_good_overrides_sweeps_and_additions_pass(overrides):
    check_overrides("fit", overrides)  # raises ConfigError on a refusal


def test_source_topics_auto_and_a_nulled_topic_pass():
    check_overrides("extract", ["source=bag", "source.root=x.mcap", "source.topics=auto"])
    check_overrides("extract", ["source=bag", "source.root=x.mcap", "source.topics.joint_states=null"])


def test_adding_a_key_that_exists_says_how_to_set_it():
    with pytest.raises(ConfigError, match=r"'seed' is already in the config: set it without '\+'"):
        check_overrides("fit", ["+seed=3"])


def test_a_stage_that_is_not_a_hydra_app_is_not_checked():
    check_overrides("models", ["whatever=1"])  # `models` takes no config: nothing to check, no error


def test_the_console_script_prints_one_line_and_exits_2(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "skidbench.pipeline.cli.main", "groundtruth", "groundtruth.orbslam.dri=/x"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [
        "skidbench groundtruth: error: unknown config key 'groundtruth.orbslam.dri'; "
        "did you mean 'groundtruth.orbslam.dir'?"
    ]
    assert not any(tmp_path.iterdir())  # nothing written (no Hydra run folder either)
