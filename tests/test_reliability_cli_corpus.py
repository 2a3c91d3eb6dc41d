"""The bad-input corpus at the command line: every case is one ``skidbench`` command (run in this process
through ``skidbench.pipeline.cli.main``, as the console script runs it) on a damaged, empty, wrong-typed,
out-of-range, non-overlapping, misspelt or unwritable input, and must end with exit status 2, exactly one
error line on stderr naming the key or file, no traceback, and every file written before unchanged (no
new dataset folder, no MLflow experiment). ONE table: ``CASES``.

The data: the AMRL fixture (tests/fixtures/amrl) taken through extract, groundtruth, split and calibrate
once per module; damaged files generated here and by tests/bad_inputs/make_corpus.py."""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from reliability_data import snapshot

from skidbench.pipeline.cli.main import main

sys.path.insert(0, str(Path(__file__).parent / "bad_inputs"))
from make_corpus import make  # noqa: E402

FIXTURE = Path(__file__).parent / "fixtures" / "amrl"
SEQS = ("grass_cv_01", "grass_ld_01", "grass_train_01", "tile_cv_01", "tile_ld_01", "tile_train_01")
# the prepared AMRL dataset ({out}: its output root, {amrl}: its data)
A = ("source=amrl_txt", "source.root={amrl}", "out_root={out}")
GT_ORB = ("groundtruth", *A, "groundtruth.method=orbslam", "groundtruth.jobs=1")
GT = "groundtruth"
NEW = "out_root={fresh}"  # an empty output root of the test's own

# (case, argv, fragments the error line must hold: the key or file, and the problem)
CASES = [
    # -- values: type and range, against the declared schema (pipeline/cli/config_schema.py) --------------
    ("horizons a list of words", ["evaluate", *A, "horizons=[abc]"], ["horizons=[abc]", "number > 0"]),
    ("horizons a word", ["evaluate", *A, "horizons=abc"], ["horizons=abc", "list"]),
    ("horizons empty", ["evaluate", *A, "horizons=[]"], ["horizons=[]", "non-empty"]),
    ("horizons negative", ["evaluate", *A, "horizons=[-6.0]"], ["horizons=[-6.0]"]),
    ("min_distance_m a word", ["evaluate", *A, "min_distance_m=far"], ["min_distance_m=far", ">= 0"]),
    ("min_rotation_deg negative", ["evaluate", *A, "min_rotation_deg=-1"], ["min_rotation_deg=-1"]),
    ("evaluate no models", ["evaluate", *A, "models=[]"], ["models=[]"]),
    ("evaluate an unknown model", ["evaluate", *A, "models=[nosuch]"], ["nosuch", "installed"]),
    ("evaluate an unknown protocol", ["evaluate", *A, "++inputs=oracle"], ["inputs=oracle", "commanded"]),
    ("settle_s a word", ["calibrate", *A, "calibrate.settle_s=abc"], ["calibrate.settle_s=abc", ">= 0"]),
    ("settle_s negative", ["calibrate", *A, "calibrate.settle_s=-1"], ["calibrate.settle_s=-1", ">= 0"]),
    ("calibrate ci above 1", ["calibrate", *A, "calibrate.ci=1.5"], ["calibrate.ci=1.5"]),
    ("fit reuse maybe", ["fit", *A, "terrain=tile", "reuse=maybe"], ["reuse=maybe", "true or false"]),
    ("fit an unknown split", ["fit", *A, "terrain=tile", "split=test"], ["split=test", "train|cv|ld"]),
    ("fit a terrain the data lacks", ["fit", *A, "terrain=sand", "track=false"], ["terrain=sand", "tile"]),
    ("split rate zero", ["split", *A, "split.rate_hz=0"], ["split.rate_hz=0", "> 0"]),
    ("allow_flagged a word", ["split", *A, "split.allow_flagged=perhaps"], ["split.allow_flagged=perhaps"]),
    ("SG window a word", ["split", *A, "split.differentiator.window=abc"], ["split.differentiator.window"]),
    ("groundtruth method unknown", [GT, *A, "groundtruth.method=slam"], ["groundtruth.method=slam"]),
    ("max_gap negative", [GT, *A, "groundtruth.max_gap=-0.5"], ["groundtruth.max_gap=-0.5"]),
    ("ORB-SLAM unit unknown", [GT, *A, "groundtruth.orbslam.unit=ms"], ["groundtruth.orbslam.unit=ms"]),
    ("extract images unknown", ["extract", *A, "extract.images=jpeg"], ["extract.images=jpeg", "ref|inline"]),
    ("extract batch zero", ["extract", *A, "extract.batch_rows=0"], ["extract.batch_rows=0", ">= 1"]),
    ("seed negative", ["extract", *A, "seed=-1"], ["seed=-1"]),
    ("wheel radius zero", ["extract", *A, "robot.wheel_radius=0"], ["robot.wheel_radius=0", "> 0"]),
    ("simulate format unknown", ["simulate", "out_root={fresh}", "format=ros3"], ["format=ros3", "mcap"]),
    ("simulate dt zero", ["simulate", "out_root={fresh}", "dt=0"], ["dt=0"]),
    ("DRIVE form unknown", ["extract", "source=drive_df", "source.root={c}", "source.form=csv",
                            "out_root={fresh}"], ["source.form=csv", "windows"]),
    ("compare dpi a word", ["compare", *A, "figures.dpi=abc"], ["figures.dpi=abc"]),
    ("discover one fold", ["discover", *A, "discover.folds=1"], ["discover.folds=1", ">= 2"]),
    # -- keys: misspelt, anywhere ---------------------------------------------------------------------
    ("misspelt key", ["split", *A, "split.rate_hx=30"], ["split.rate_hx", "split.rate_hz"]),
    ("misspelt top-level key", ["evaluate", *A, "horizonz=[6]"], ["horizonz", "horizons"]),
    ("misspelt group option", ["fit", *A, "terrain=tile", "model=edf"], ["model=edf", "model=edd"]),
    ("misspelt key of another stage", ["extract", *A, "groundtruth.methd=vo"],
     ["groundtruth.methd", "groundtruth.method"]),
    ("bad value of another stage's key", ["extract", *A, "groundtruth.method=slam"],
     ["groundtruth.method=slam"]),
    # -- the output root --------------------------------------------------------------------------------
    ("out_root under a file", ["datasets", "out_root={c}/bag_not_a_bag.bag/out"],
     ["out_root=", "not a folder"]),
    # -- data: missing, damaged, empty, wrong-typed, non-overlapping -------------------------------------
    ("bag path missing", ["extract", "source=bag", "source.root={fresh}/nothing.bag", "out_root={fresh}"],
     ["nothing.bag", "no such file"]),
    ("bag truncated", ["extract", "source=bag", "source.root={c}/bag_truncated.bag", "source.terrain=tile",
                       "source.category=cv", "out_root={fresh}"], ["bag_truncated.bag", "truncated"]),
    ("bag not a bag", ["extract", "source=bag", "source.root={c}/bag_not_a_bag.bag", "source.terrain=tile",
                       "source.category=cv", "out_root={fresh}"], ["bag_not_a_bag.bag"]),
    ("bag folder empty", ["extract", "source=bag", "source.root={c}/empty", "out_root={fresh}"], ["empty"]),
    ("compare with nothing evaluated", ["compare", "out_root={fresh}"], ["evaluate"]),
    ("groundtruth before extract", [GT, "source=amrl_txt", "source.root={amrl}", NEW],
     ["manifest.json", "skidbench extract"]),
    ("AMRL wrong column count", ["extract", "source=amrl_txt", "source.root={c}/amrl_bad", NEW],
     ["1.txt", "expected 7 values"]),
    ("pose table missing", [GT, *A, "groundtruth.method=pose_topic", "groundtruth.pose_topic.key=nope"],
     ["nope.parquet", "groundtruth.pose_topic.key"]),
    ("ORB-SLAM times never overlap", [*GT_ORB, "groundtruth.orbslam.dir={c}/orb_far"],
     ["/orb_far/", ".txt: poses", "never overlap"]),
    ("ORB-SLAM non-numeric in an 8-field row", [*GT_ORB, "groundtruth.orbslam.dir={c}/orb_text"],
     ["/orb_text/", ".txt:3: non-numeric value 'abc'"]),
    ("KITTI without its times file", [*GT_ORB, "groundtruth.orbslam.dir={c}/orb_kitti"],
     ["/orb_kitti/", "groundtruth.orbslam.times_pattern"]),
    ("ORB-SLAM folder without the files", [*GT_ORB, "groundtruth.orbslam.dir={c}/empty"],
     ["/empty:", "no ORB-SLAM file", "groundtruth.orbslam.dir"]),
    ("DRIVE windows without calib_step", ["extract", "source=drive_df", "source.root={c}/drive_nostep",
                                          "robot=husky", NEW], ["husky_windows.parquet", "calib_step"]),
    ("DRIVE file of another robot", ["extract", "source=drive_df", "source.root={c}/drive_ok",
                                     "robot=warthog", NEW],
     ["husky_windows.parquet", "robot=warthog", "per wheel radian"]),
    ("DRIVE file renamed, another robot's", ["extract", "source=drive_df", "source.root={c}/drive_renamed",
                                             "source.file=data.parquet", "robot=warthog", NEW],
     ["data.parquet", "robot=warthog", "per wheel radian"]),
    ("DRIVE truncated Parquet", ["extract", "source=drive_df", "source.root={c}",
                                 "source.file=drive_truncated_raw.parquet", "out_root={fresh}"],
     ["drive_truncated_raw.parquet", "not a readable Parquet"]),
    ("DRIVE file missing", ["extract", "source=drive_df", "source.root={c}/drive_ok",
                            "source.file=nope.parquet", "robot=husky", NEW],
     ["drive_ok/nope.parquet", "no such file", "husky_windows.parquet"]),
    ("DRIVE root missing", ["extract", "source=drive_df", "source.root={c}/nothing", NEW],
     ["source.root={c}/nothing", "no such folder"]),
    ("DRIVE folder empty", ["extract", "source=drive_df", "source.root={c}/empty", NEW],
     ["empty/husky_windows.parquet", "holds no DRIVE file"]),
    ("DRIVE folder, source.file not set (make reproduce SOURCE=drive_df DATA=<dir>)",
     ["extract", "source=drive_df", "source.root={c}/drive_renamed", NEW],
     ["husky_windows.parquet: no such file", "it holds data.parquet", "set source.file"]),
    ("DRIVE two terrains for one file", ["split", "source=drive_df", "source.root={c}/drive_ok",
                                         "source.terrain=[a,b]", NEW],
     ["source.terrain=", "one terrain per file"]),
    ("DRIVE with a bag source's setting", ["extract", "source=drive_df", "source.root={c}/drive_ok",
                                           "source.topics=atuo", NEW],
     ["source.topics=atuo", "source=drive_df"]),
    ("DRIVE pickle calling os.system", ["extract", "source=drive_df", "source.root={c}",
                                        "source.file=drive_unsafe.pkl", NEW], ["drive_unsafe.pkl", "unsafe"]),
    ("DRIVE lifted robot", ["extract", "source=drive_df", "source.root={c}", "robot=husky",
                            "source.file=drive_lifted_windows.parquet", NEW],
     ["does not move while its wheels turn"]),
    # -- a released benchmark (docs/publishing.md): bundles, predictions files, named datasets ------------
    ("import a folder that is no bundle", ["import", "{c}/empty", NEW], ["empty/SHA256SUMS", "missing"]),
    ("import without its folder", ["import", NEW], ["missing argument", "skidbench import <dir>"]),
    ("export a dataset the root lacks", ["export", "nosuch", "{fresh}/bundle", "out_root={out}"],
     ["nosuch", "no dataset"]),
    ("export real data without a licence", ["export", "{name}", "{fresh}/bundle", "out_root={out}"],
     ["bundle.licence", "amrl_txt"]),
    ("score a predictions file that is not there", ["score", "{name}", "--predictions", "{c}/nope.csv",
                                                    "out_root={out}"], ["nope.csv", "no such file"]),
    ("score a predictions file of another format", ["score", "{name}", "--predictions",
                                                    "{amrl}/Grass/Train/cmd/1.txt", "out_root={out}"],
     ["cmd/1.txt", ".parquet or .csv"]),
    ("publish a dataset the root lacks", ["publish", "nosuch", "{fresh}/site", "out_root={out}"],
     ["nosuch", "no dataset"]),
    ("two roots at one dataset name", ["split", "source=amrl_txt", "source.root={amrl2}",
                                       "source.dataset={name}", "out_root={out}"],
     ["{amrl2}", "already holds"]),
]  # fmt: skip


def _orb_rows(t0: float, n: int = 40, rate: float = 10.0) -> list[str]:
    return [f"{t0 + i / rate:.6f} 0 0 {0.05 * i:.6f} 0 0 0 1" for i in range(n)]


def _write_corpus(c: Path) -> None:
    make(c)
    (c / "empty").mkdir()
    for name in ("orb_far", "orb_text", "orb_kitti"):
        (c / name).mkdir()
    for seq in SEQS:  # the fixture's bag clock runs 1000..1008 s: these run 100..104 s
        (c / "orb_far" / f"{seq}.txt").write_text("\n".join(_orb_rows(100.0)) + "\n")
        rows = _orb_rows(1000.0)
        rows[1] = rows[1].replace(" 0 0 0 1", " abc 0 0 1")  # line 3 after the comment line
        (c / "orb_text" / f"{seq}.txt").write_text(
            "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n"
        )
        kitti = [
            " ".join(["1", "0", "0", f"{0.05 * i}", "0", "1", "0", "0", "0", "0", "1", "0"]) for i in range(5)
        ]
        (c / "orb_kitti" / f"{seq}.txt").write_text("\n".join(kitti) + "\n")
    bad = c / "amrl_bad"
    shutil.copytree(FIXTURE, bad)
    cmd = bad / "Grass" / "ConstantVel" / "cmd" / "1.txt"  # the first sequence read: nothing written yet
    lines = cmd.read_text().splitlines()
    cmd.write_text("\n".join([lines[0] + ",9", *lines[1:]]) + "\n")  # 8 values in a row
    from test_sources_drive_synthetic import drive_like_frame

    frame = drive_like_frame([(0.5, 0.0), (0.4, 0.3), (0.6, -0.2), (0.3, 0.1), (0.5, 0.4)])[0]
    for name, df in (("drive_ok", frame), ("drive_nostep", frame.drop(columns=["calib_step"]))):
        (c / name).mkdir()
        df.to_parquet(c / name / "husky_windows.parquet")
    (c / "drive_renamed").mkdir()  # Husky windows under a name that says nothing: the content tells
    frame.to_parquet(c / "drive_renamed" / "data.parquet")


@pytest.fixture(scope="module")
def prepared(tmp_path_factory) -> dict[str, str]:
    """Paths of the case table: the prepared dataset's output root and data, the corpus folder."""
    base = tmp_path_factory.mktemp("cli_corpus")
    amrl, out, c = base / "amrl", base / "out", base / "corpus"
    shutil.copytree(FIXTURE, amrl)
    shutil.copytree(FIXTURE, base / "amrl2")  # another recording (a copy would be the same dataset)
    (base / "amrl2" / "notes.txt").write_text("recorded on another day")
    c.mkdir()
    _write_corpus(c)
    for stage_args in (["extract"], ["groundtruth"], ["split"], ["calibrate", "track=false"]):
        code, err = _run([stage_args[0], f"source.root={amrl}", "source=amrl_txt", f"out_root={out}",
                          *stage_args[1:]])  # fmt: skip
        assert code == 0, err
    (name,) = [d.name for d in out.iterdir() if d.name.startswith("amrl-")]
    return {"out": str(out), "amrl": str(amrl), "amrl2": str(base / "amrl2"), "c": str(c), "name": name}


def _run(argv: list[str]) -> tuple[int, str]:
    """``skidbench <argv>`` in this process: (exit status, stderr)."""
    import contextlib
    import io

    err = io.StringIO()
    code = 0
    argv0 = sys.argv
    try:
        with contextlib.redirect_stderr(err):
            main(argv)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    finally:
        sys.argv = argv0
    return code, err.getvalue()


def _experiments(out: Path) -> list[str]:
    """The MLflow experiments of the output root's store (MLflow's own ``Default`` left out)."""
    db = out / "mlflow.db"
    if not db.is_file():
        return []
    with sqlite3.connect(db) as con:
        return sorted(r[0] for r in con.execute("select name from experiments") if r[0] != "Default")


def _state(out: Path) -> tuple[dict[str, str], list[str], list[str]]:
    folders = (
        sorted(p.name for p in out.iterdir() if p.is_dir() and p.name != "hydra") if out.is_dir() else []
    )
    return snapshot(out), folders, _experiments(out)


def _clear_markers(out: Path) -> None:
    for marker in out.glob("*/.stamps/*.failed.json"):
        marker.unlink()


@pytest.mark.parametrize(("case", "argv", "fragments"), CASES, ids=[c[0] for c in CASES])
def test_each_bad_input_is_one_line_exit_2_and_changes_nothing(prepared, tmp_path, case, argv, fragments):
    paths = {**prepared, "fresh": str(tmp_path / "fresh")}
    argv = [a.format(**paths) for a in argv]
    out, fresh = Path(prepared["out"]), tmp_path / "fresh"
    before = _state(out), _state(fresh)
    try:
        code, err = _run(argv)
    finally:
        after = _state(out), _state(fresh)
        _clear_markers(out)
    assert code == 2, err
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert len(errors) == 1, err
    assert errors[0].startswith(f"skidbench {argv[0]}: error: "), errors
    for fragment in fragments:
        assert fragment.format(**paths) in errors[0], errors[0]
    assert after == before  # nothing written before changed; no dataset folder, no experiment left


def test_the_corpus_has_at_least_40_cases():
    assert len(CASES) >= 40
    assert len({c[0] for c in CASES}) == len(CASES)


def test_a_failed_extract_stops_the_stages_downstream_until_it_succeeds(tmp_path):
    data, out = tmp_path / "amrl", tmp_path / "out"
    shutil.copytree(FIXTURE, data)
    args = ["source=amrl_txt", f"source.root={data}", f"out_root={out}"]
    for s in ("extract", "groundtruth"):
        assert _run([s, *args])[0] == 0
    cmd = data / "Tile" / "Train" / "cmd" / "1.txt"
    good = cmd.read_text()
    cmd.write_text("garbage\n" + good)  # the source damaged in place
    code, err = _run(["extract", *args])
    assert code == 2 and "1.txt" in err
    ds = next(d for d in out.iterdir() if d.name.startswith("amrl-"))
    before = snapshot(out)
    for s in ("groundtruth", "split"):
        code, err = _run([s, *args])
        assert code == 2, err
        (line,) = [ln for ln in err.splitlines() if ": error: " in ln]
        assert "last `skidbench extract` failed" in line and "re-run skidbench extract" in line, line
    assert snapshot(out) == before
    cmd.write_text(good)
    for s in ("extract", "groundtruth", "split"):
        assert _run([s, *args])[0] == 0
    assert not list(ds.glob(".stamps/*.failed.json"))


def test_datasets_lists_only_folders_with_an_extracted_table(prepared, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(prepared["out"], out, ignore=shutil.ignore_patterns("hydra"))
    (out / "bags-empty-000000").mkdir()
    (out / "bags-empty-000000" / "dataset.json").write_text('{"schema": 1, "name": "bags-empty-000000"}')
    capsys.readouterr()
    assert _run(["datasets", f"out_root={out}"])[0] == 0
    listed = capsys.readouterr().out
    assert prepared["name"] in listed and "bags-empty-000000" not in listed


def test_other_stages_settings_are_ignored_with_a_note(prepared):
    over = ["groundtruth.method=pose_topic", "groundtruth.pose_topic.key=gt_pose", "split.allow_flagged=true"]
    code, err = _run(["extract", *(a.format(**prepared) for a in A), *over])
    assert code == 0, err
    assert "note: groundtruth.method is another stage's setting; extract ignores it" in err


def _unwritable_folder(tmp_path: Path) -> Path:
    """A folder this process cannot write into: a read-only one of its own, or (as root, whom
    permissions do not stop) /sys, read-only in containers; else the test is skipped."""
    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        return ro
    try:
        Path("/sys/.skidbench-probe").touch()
    except OSError:
        return Path("/sys")
    Path("/sys/.skidbench-probe").unlink()
    pytest.skip("no unwritable folder to test with")


def test_an_unwritable_output_root_is_one_line_at_the_command_line(tmp_path):
    ro = _unwritable_folder(tmp_path)
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "skidbench.pipeline.cli.main", "datasets", f"out_root={ro}/out"],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    finally:
        if ro != Path("/sys"):
            ro.chmod(0o755)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()]
    assert f"out_root={ro}/out: cannot write there" in proc.stderr
    assert not (ro / "out").exists()


def test_the_orbslam_overlap_check_accepts_the_right_times(prepared, tmp_path):
    """The control of the non-overlap case: the same file on the recording's clock is accepted."""
    orb = tmp_path / "orb"
    orb.mkdir()
    for seq in SEQS:
        (orb / f"{seq}.txt").write_text("\n".join(_orb_rows(1000.0, n=80)) + "\n")
    out = tmp_path / "out"
    shutil.copytree(prepared["out"], out, ignore=shutil.ignore_patterns("hydra"))
    args = [a.format(**{**prepared, "out": str(out)}) for a in GT_ORB]
    code, err = _run([*args, f"groundtruth.orbslam.dir={orb}"])
    assert code == 0, err
    tum = next(out.glob("amrl-*/groundtruth/grass_cv_01.tum"))
    t = np.loadtxt(tum, comments="#")[:, 0]
    assert 1000.0 <= t[0] < t[-1] <= 1008.0
    assert pd.notna(t).all()


UT_BAG = "ut_automata_ikd_2023-03-23-10-44-04.bag"
UT_TOPICS = (
    "source.terrain=lab", "source.category=train",
    "source.topics.cmd_vel.topic=/vesc_drive", "source.topics.cmd_vel.type=geometry_msgs/msg/TwistStamped",
    "source.topics.odom.topic=/odom", "source.topics.imu.topic=/vectornav/IMU",
    "source.topics.joint_states.required=false",
)  # fmt: skip


@pytest.mark.shared
def test_the_real_bag_copied_and_damaged(shared_real, tmp_path):
    """The UT AUTOmata bag (../shared): an ORB-SLAM file of another clock is refused at groundtruth; the
    bag damaged in place makes extract fail, and groundtruth then names extract to re-run."""
    data, out, orb = tmp_path / "data", tmp_path / "out", tmp_path / "orb"
    data.mkdir()
    orb.mkdir()
    bag = data / UT_BAG
    shutil.copy(shared_real / "bags" / UT_BAG, bag)
    args = ["source=bag", f"source.root={bag}", f"out_root={out}", *UT_TOPICS]
    assert _run(["extract", *args])[0] == 0
    (orb / f"{bag.stem}.txt").write_text("\n".join(_orb_rows(0.0, n=100)) + "\n")  # relative times
    before = snapshot(out)
    code, err = _run(["groundtruth", *args, "groundtruth.method=orbslam", f"groundtruth.orbslam.dir={orb}"])
    (line,) = [ln for ln in err.splitlines() if ": error: " in ln]
    assert code == 2 and f"{orb}/{bag.stem}.txt" in line and "never overlap" in line, err
    _clear_markers(out)
    assert snapshot(out) == before
    bag.write_bytes(bag.read_bytes()[: bag.stat().st_size // 3])  # damaged in place
    code, err = _run(["extract", *args])
    assert code == 2 and UT_BAG in err, err
    code, err = _run(["groundtruth", *args, "groundtruth.method=orbslam", f"groundtruth.orbslam.dir={orb}"])
    (line,) = [ln for ln in err.splitlines() if ": error: " in ln]
    assert code == 2 and "re-run skidbench extract" in line, err


@pytest.mark.slow
def test_a_refused_robot_leaves_the_dataset_as_it_was_and_the_right_one_runs(prepared, tmp_path):
    """A Husky recording extracted and split as a Husky, then extracted as a Warthog: refused in one line
    before anything is written, no failure recorded (nothing it left is stale), and `evaluate robot=husky`
    runs on the Husky extraction that is still there."""
    out = tmp_path / "out"
    args = ["source=drive_df", f"source.root={prepared['c']}/drive_ok", f"out_root={out}"]
    for s in ("extract", "groundtruth", "split"):
        code, err = _run([s, *args, "robot=husky"])
        assert code == 0, err
    before = snapshot(out)
    code, err = _run(["extract", *args, "robot=warthog"])
    (line,) = [ln for ln in err.splitlines() if ": error: " in ln]
    assert code == 2 and "robot=warthog" in line and "per wheel radian" in line, err
    assert snapshot(out) == before and not list(out.glob("*/.stamps/*.failed.json"))
    # the Husky's own constants (no calibrate stage: the refusal is the point, not the calibration)
    code, err = _run(
        ["evaluate", *args, "robot=husky", "models=[edd]", "horizons=[2.0]", "calibrate.use=false"]
    )
    assert code == 0, err
