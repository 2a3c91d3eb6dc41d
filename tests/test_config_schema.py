"""The declared schema (pipeline/cli/config_schema.py: the settings dataclasses that are configs, and the
SCHEMA table of the keys not yet in one): every key of every stage's config, under every group option, is
declared once; every shipped default passes; a value out of type or range is one line naming the key, the
value and what is allowed."""

from __future__ import annotations

import dataclasses
import functools
from importlib import resources

import pytest
from omegaconf import OmegaConf

from skidbench.pipeline.cli.config_schema import (
    ROOTS,
    SCHEMA,
    STRUCTURED,
    check_value,
    package_of,
    spec_for,
    spec_of,
    structured_keys,
)
from skidbench.pipeline.cli.overrides import _compose, check_overrides, leaves, validate
from skidbench.pipeline.core.errors import ConfigError
from skidbench.pipeline.core.layout import root_from_cfg

STAGES = sorted(p.name[:-5] for p in resources.files("skidbench.conf").iterdir() if p.name.endswith(".yaml"))
GROUPS = {
    g: sorted(
        p.name[:-5]
        for p in resources.files("skidbench.conf").joinpath(g).iterdir()
        if p.name.endswith(".yaml")
    )
    for g in ("robot", "source", "scale", "model")
}


@functools.cache
def _composed(stage: str) -> object:
    """``_compose(stage, [])``, composed once per process (collection composes every stage; the tests
    only read it)."""
    return _compose(stage, [])


def _configs():
    for stage in STAGES:
        yield stage, []
        cfg = _composed(stage)
        for group, options in GROUPS.items():
            if group not in cfg.hydra.runtime.choices:
                continue
            for option in options:
                yield stage, [f"{group}={option}"]


@pytest.mark.parametrize(("stage", "overrides"), list(_configs()), ids=lambda v: str(v))
def test_every_key_is_declared_and_every_default_is_valid(stage, overrides):
    cfg = _compose(stage, overrides) if overrides else _composed(stage)
    undeclared = [key for key, _ in leaves(cfg) if spec_for(key) is None]
    assert not undeclared, f"declare these in pipeline/cli/config_schema.py SCHEMA: {undeclared}"
    validate(cfg)


@pytest.mark.parametrize(
    ("key", "value", "allowed"),
    [
        ("calibrate.settle_s", -1, ">= 0"),
        ("calibrate.settle_s", "abc", ">= 0"),
        ("calibrate.settle_s", float("nan"), ">= 0"),
        ("horizons", "abc", "list"),
        ("horizons", ["abc"], "number > 0"),
        ("horizons", [], "non-empty"),
        ("reuse", "maybe", "true or false"),
        ("reuse", 1, "true or false"),
        ("split.differentiator.window", 9.5, "integer"),
        ("groundtruth.orbslam.unit", "ms", "auto|s|ns"),
        ("source.topics.cmd_vel.required", "yes", "true or false"),
        ("scale.simulate.durations.train.tile", -5, ">= 0"),
        ("split.rate_hz", True, "number"),
    ],
)
def test_a_bad_value_is_one_line_naming_key_value_and_what_is_allowed(key, value, allowed):
    with pytest.raises(ConfigError) as exc:
        check_value(key, value)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(f"invalid value {key}=") and allowed in msg, msg


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("calibrate.settle_s", 0),
        ("calibrate.settle_s", 0.5),
        ("horizons", [1, 6.0]),
        ("split.differentiator.window", 9.0),
        ("terrains", None),
        ("inputs", "measured"),
        ("split.allow_flagged", True),
        ("source.form", "windows"),
        ("train_dataset", "sim-mini"),
    ],
)
def test_a_good_value_passes(key, value):
    check_value(key, value)


def test_the_keys_other_issues_add_are_declared():
    for key in ("inputs", "split.allow_flagged", "source.form", "train_dataset"):
        assert spec_for(key) is not None, key


# -- the settings dataclasses that are configs (STRUCTURED): one declaration per key ---------------------
def test_a_structured_key_is_declared_by_its_dataclass_only():
    twice = [k for k in SCHEMA if any(k.startswith(f"{package_of(p)}.") for p in STRUCTURED)]
    assert not twice, f"declared by a settings dataclass and again in SCHEMA: {twice}"
    keys = list(structured_keys())
    leaves = [k for k in keys if not any(o.startswith(f"{k}.") for o in keys)]
    assert "split.consistency.min_rows" in leaves and "split.consistency" not in leaves
    for key in leaves:
        assert spec_for(key) is not None, key


@pytest.mark.parametrize("entry", sorted(STRUCTURED))
def test_the_composed_section_is_its_dataclass_with_its_defaults(entry):
    cls, package = STRUCTURED[entry], package_of(entry)
    stage = entry.partition("/")[2] or _stage_with(package)  # bundle/export: export's bundle section
    composed = OmegaConf.select(_composed(stage), package)
    # as written, before resolving: publish.dir is ??? (an argument), mlflow.experiment skidbench-${dataset}
    assert OmegaConf.to_container(composed) == OmegaConf.to_container(OmegaConf.structured(cls))
    if not OmegaConf.missing_keys(composed) and "${" not in str(OmegaConf.to_container(composed)):
        assert OmegaConf.to_object(composed) == cls()


def _stage_with(package: str) -> str:
    return next(s for s in STAGES if OmegaConf.is_config(OmegaConf.select(_composed(s), package)))


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("calibrate.settle_s=abc", "invalid value calibrate.settle_s=abc: allowed a number >= 0 (s since"),
        ("calibrate.settle_s=-1", "invalid value calibrate.settle_s=-1: allowed a number >= 0"),
        ("calibrate.use=1", "invalid value calibrate.use=1: allowed true or false"),
        ("calibrate.min_rows=9.5", "invalid value calibrate.min_rows=9.5: allowed an integer >= 1"),
        ("calibrate.settle_s=null", "invalid value calibrate.settle_s=null: allowed a number >= 0"),
        ("calibrate.setle_s=1", "unknown config key 'calibrate.setle_s'; did you mean 'calibrate.settle_s'?"),
    ],
)
def test_a_mistyped_or_misspelt_structured_override_is_one_line_naming_the_key(override, message):
    with pytest.raises(ConfigError) as exc:
        foreign, cfg = check_overrides("calibrate", [override])
        validate(cfg)
    assert "\n" not in str(exc.value) and str(exc.value).startswith(message), str(exc.value)


# -- root keys declared by a dataclass (ROOTS): common.yaml's and a stage's own keys -----------------------
def test_a_root_key_is_declared_by_its_dataclass_only():
    for name, cls in ROOTS.items():
        for f in dataclasses.fields(cls):
            # a key another stage (not yet a dataclass) shares is declared there alike
            assert f.name not in SCHEMA or SCHEMA[f.name] == spec_of(cls, f.name), (name, f.name)
            assert spec_for(f.name) == spec_of(cls, f.name), f.name


def test_the_composed_root_keys_are_their_dataclass_with_its_defaults():
    cfg = _composed("evaluate")
    data = OmegaConf.to_container(cfg, resolve=False)  # out_root, dataset: interpolations
    for name in ("common", "evaluate"):
        assert ROOTS[name](**{f.name: data[f.name] for f in dataclasses.fields(ROOTS[name])}) == ROOTS[name]()
    assert root_from_cfg(cfg, ROOTS["evaluate"]).horizons == [6.0, 0.5, 1.0, 2.0, 4.0]


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("seeds=1.5", "invalid value seeds=1.5: allowed an integer >= 1 and <= 100"),
        (
            "horizons=[6,abc]",
            "invalid value horizons=[6,abc]: allowed a non-empty list [a,b,...], each a number",
        ),
        ("force=1", "invalid value force=1: allowed true or false"),
        ("inputs=comanded", "invalid value inputs=comanded: allowed one of commanded|response|measured"),
        ("splits=[cv,test]", "invalid value splits=[cv,test]: allowed a non-empty list"),
        ("modles=[ideal]", "unknown config key 'modles'; did you mean 'models'?"),
    ],
)
def test_a_mistyped_or_misspelt_root_override_is_one_line_naming_the_key(override, message):
    with pytest.raises(ConfigError) as exc:
        foreign, cfg = check_overrides("evaluate", [override])
        validate(cfg)
    assert "\n" not in str(exc.value) and str(exc.value).startswith(message), str(exc.value)


@pytest.mark.parametrize(
    ("stage", "override", "message"),
    [
        ("publish", "publish.dpi=abc", "invalid value publish.dpi=abc: allowed an integer >= 20 and <= 600"),
        ("publish", "publish.dpi=5", "invalid value publish.dpi=5: allowed an integer >= 20 and <= 600"),
        ("publish", "publish.figures=1", "invalid value publish.figures=1: allowed true or false"),
        ("publish", "publish.dirr=site", "unknown config key 'publish.dirr'; did you mean 'publish.dir'?"),
        ("score", "score.check=yes", "invalid value score.check=yes: allowed true or false"),
        ("score", "score.nmae=x", "unknown config key 'score.nmae'; did you mean 'score.name'?"),
        ("card", "card.paper=2", "invalid value card.paper=2: allowed true or false"),
        ("card", "card.papr=true", "unknown config key 'card.papr'; did you mean 'card.paper'?"),
        ("compare", "horizon=0", "invalid value horizon=0: allowed a number > 0 (s)"),
        ("compare", "log_to_mlflow=yes", "invalid value log_to_mlflow=yes: allowed true or false"),
        ("compare", "horizn=1", "unknown config key 'horizn'; did you mean 'horizon'?"),
        (
            "discover",
            "discover.placebo=maybe",
            "invalid value discover.placebo=maybe: allowed one of auto|True|False",
        ),
        ("discover", "discover.folds=1", "invalid value discover.folds=1: allowed an integer >= 2"),
        (
            "discover",
            "discover.alpah=0.1",
            "unknown config key 'discover.alpah'; did you mean 'discover.alpha'?",
        ),
        ("evaluate", "mlflow.timeout_s=0", "invalid value mlflow.timeout_s=0: allowed a number > 0 (s)"),
        (
            "compare",
            "mlflow.experimnt=x",
            "unknown config key 'mlflow.experimnt'; did you mean 'mlflow.experiment'?",
        ),
        ("groundtruth", "groundtruth.method=slam", "invalid value groundtruth.method=slam: allowed one of"),
        ("groundtruth", "groundtruth.jobs=0", "invalid value groundtruth.jobs=0: allowed an integer >= 1"),
        (
            "groundtruth",
            "groundtruth.pose_topic.tf_max_gap=abc",
            "invalid value groundtruth.pose_topic.tf_max_gap=abc: allowed a number > 0 (or null) (s; null: ",
        ),
        (
            "groundtruth",
            "groundtruth.orbslam.max_diff=0",
            "invalid value groundtruth.orbslam.max_diff=0: allowed a number > 0 (s)",
        ),
        (
            "groundtruth",
            "groundtruth.loop_bound.rotational=-1",
            "invalid value groundtruth.loop_bound.rotational=-1: allowed a number > 0",
        ),
        (
            "groundtruth",
            "groundtruth.pose_topic.stmp=stamp_ns",
            "unknown config key 'groundtruth.pose_topic.stmp'; did you mean 'groundtruth.pose_topic.stamp'?",
        ),
        (
            "groundtruth",
            "groundtruth.max_gpa=1",
            "unknown config key 'groundtruth.max_gpa'; did you mean 'groundtruth.max_gap'?",
        ),
        (
            "export",
            "bundle.release=public",
            "invalid value bundle.release=public: allowed one of withheld|open",
        ),
        ("export", "bundle.licnce=MIT", "unknown config key 'bundle.licnce'; did you mean 'bundle.licence'?"),
        ("import", "bundle.answrs=x", "unknown config key 'bundle.answrs'; did you mean 'bundle.answers'?"),
        ("import", "bundle.name=[a,b]", "invalid value bundle.name=[a,b]: allowed a string (or null)"),
        (
            "evaluate",
            "groundtruth.max_gap=abc",
            "invalid value groundtruth.max_gap=abc: allowed a number > 0 (s)",
        ),
        ("simulate", "format=ros3", "invalid value format=ros3: allowed one of ros1|ros2|mcap"),
        ("simulate", "dt=0.1", "invalid value dt=0.1: allowed a number > 0 and <= 0.01 (s, physics step)"),
        ("simulate", "jobs=0", "invalid value jobs=0: allowed an integer >= 1"),
        ("simulate", "images=2", "invalid value images=2: allowed true or false"),
        ("simulate", "only=grass_cv_00", "invalid value only=grass_cv_00: allowed a list [a,b,...]"),
        ("simulate", "rates.imu=0", "invalid value rates.imu=0: allowed a number > 0 (Hz)"),
        ("simulate", "rates.imu=abc", "invalid value rates.imu=abc: allowed a number > 0 (Hz)"),
        (
            "simulate",
            "sensors.gyro=-1",
            "invalid value sensors.gyro=-1: allowed a number >= 0 (1-sigma noise)",
        ),
        ("simulate", "formt=ros2", "unknown config key 'formt'; did you mean 'format'?"),
        ("calibrate", "force=yes", "invalid value force=yes: allowed true or false"),
        ("calibrate", "trak=false", "unknown config key 'trak'; did you mean 'track'?"),
        ("fit", "split=test", "invalid value split=test: allowed one of train|"),
        ("fit", "reuse=2", "invalid value reuse=2: allowed true or false"),
        ("fit", "terain=tile", "unknown config key 'terain'; did you mean 'terrain'?"),
        ("publish", "rank_by=[a,b]", "invalid value rank_by=[a,b]: allowed a string"),
        ("publish", "rank_bi=mean4", "unknown config key 'rank_bi'; did you mean 'rank_by'?"),
        (
            "groundtruth",
            "+groundtruth.vo.n_featres=900",
            "unknown config key 'groundtruth.vo.n_featres'; did you mean 'groundtruth.vo.n_features'?",
        ),
        (
            "groundtruth",
            "+groundtruth.vo.stride=abc",
            "invalid value groundtruth.vo.stride=abc: allowed an integer",
        ),
        ("simulate", "rates.imuu=100", "unknown config key 'rates.imuu'; did you mean 'rates.imu'?"),
    ],
)
def test_a_mistyped_or_misspelt_section_override_of_another_stage_is_one_line(stage, override, message):
    with pytest.raises(ConfigError) as exc:
        foreign, cfg = check_overrides(stage, [override])
        validate(cfg)
    assert "\n" not in str(exc.value) and str(exc.value).startswith(message), str(exc.value)


def test_discover_takes_the_settings_of_the_stages_it_runs_for_a_raw_source():
    """`skidbench discover source=...` runs extract and split itself: their sections are its own (a DRIVE
    recording with flagged sequences needs ``split.drop_flagged=true``), never "another stage's setting"."""
    from skidbench.pipeline.cli.api import _with_stage

    args = ["split.drop_flagged=true", "extract.batch_rows=64"]
    dropped, cfg = check_overrides("discover", args)
    assert dropped == [] and cfg.split.drop_flagged is True and cfg.extract.batch_rows == 64
    assert _with_stage(cfg, "split").split.drop_flagged is True  # what prepare_splits hands the split stage
    with pytest.raises(ConfigError, match="split.drop_flagged"):
        check_overrides("discover", ["split.drop_flaged=true"])


def test_the_groundtruth_section_reads_the_sources_method_and_takes_free_vo_options():
    """``groundtruth.method`` and ``groundtruth.pose_topic.key`` default to what the source names (a raw
    source's pose table); ``+groundtruth.vo.*`` add the stereo VO's options (VOConfig's fields, checked
    at the start); ``orbslam.dir`` is unset until the method needs it."""
    from skidbench.pipeline.groundtruth.app import GroundTruthConfig

    _, cfg = check_overrides("groundtruth", ["source=drive_df", "+groundtruth.vo.n_features=300"])
    job = GroundTruthConfig.from_cfg(cfg)
    assert (job.gt.method, job.gt.pose_topic.key) == ("pose_topic", "gt_pose")
    assert job.gt.vo == {"n_features": 300} and job.gt.orbslam.dir is None
    assert job.gt.tf_max_gap == job.gt.max_gap == 0.5
    _, cfg = check_overrides("groundtruth", [])
    assert GroundTruthConfig.from_cfg(cfg).gt.method == "vo"


def test_a_bundle_key_of_the_other_release_stage_is_reported_as_its_setting():
    """export and import give ``bundle`` different keys: ``export bundle.answers=x`` is import's setting,
    dropped with a note (as ``make reproduce ARGS=...`` passes it to every stage), never accepted as
    export's own."""
    dropped, cfg = check_overrides("export", ["bundle.answers=x", "bundle.release=open"])
    assert dropped == ["bundle.answers=x"] and "answers" not in cfg.bundle and cfg.bundle.release == "open"
    dropped, cfg = check_overrides("import", ["bundle.release=open", "bundle.name=n"])
    assert dropped == ["bundle.release=open"] and cfg.bundle.name == "n"


def test_the_discover_section_takes_the_searchs_defaults_from_one_place():
    """The significance rule's and the search's keys (``discover.alpha`` ...) are null in the section: the
    search's own defaults (DiscoverSettings, which an augmented model's fit uses too) are declared once;
    a value given still overrides them, and is still checked."""
    import dataclasses as dc

    from skidbench.benchmark.discovery.settings import DiscoverOptions
    from skidbench.models.augmented.fit import DiscoverSettings

    _, cfg = check_overrides("discover", [])
    opts = OmegaConf.to_object(cfg.discover)
    assert opts.search(0) == DiscoverSettings()
    shared = {f.name for f in dc.fields(DiscoverSettings)} & {f.name for f in dc.fields(DiscoverOptions)}
    assert shared and all(getattr(opts, name) is None for name in shared)
    _, cfg = check_overrides("discover", ["discover.folds=3", "discover.open_ended=false"])
    search = OmegaConf.to_object(cfg.discover).search(7)
    assert (search.folds, search.open_ended, search.seed, search.alpha) == (
        3,
        False,
        7,
        DiscoverSettings().alpha,
    )


def test_orbslam_without_its_folder_is_one_line_naming_the_key(tmp_path):
    """``groundtruth.orbslam.dir`` is null until the method needs it: then one line says what to set (it
    was ``???``, whose read ended in an OmegaConf traceback)."""
    from types import SimpleNamespace

    from skidbench.pipeline.core.layout import Layout
    from skidbench.pipeline.groundtruth.app import GroundTruthConfig, sequence_groundtruth
    from skidbench.pipeline.groundtruth.settings import GroundTruthSettings

    job = GroundTruthConfig(GroundTruthSettings(method="orbslam"), robot={})
    with pytest.raises(ConfigError, match=r"^groundtruth.method=orbslam: set groundtruth.orbslam.dir="):
        sequence_groundtruth(job, Layout(tmp_path, "d"), None, SimpleNamespace(name="s"))
