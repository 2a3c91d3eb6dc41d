"""DRIVE's own files: pandas pickles (``raw_dataframe.pkl``, ``torch_ready_dataframe.pkl``,
``slip_dataset_all.pkl``) read through the restricted unpickler, as pandas 1.5, 2.0-2.3, 3.0 and the
installed one write them, and one file DRIVE published (pandas older than 1.5: its blocks are
``functools.partial(new_block, ndim=2)``); anything a dataframe does not hold is refused as unsafe, before
it is imported or called."""

from __future__ import annotations

import functools
import gzip
import pickle
import re
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from skidbench.pipeline.core.errors import SourceError
from skidbench.pipeline.sources.drive_files import ALLOWED_GLOBALS, UnsafePickleError, detect_form, read_frame

FIX = Path(__file__).parent / "fixtures" / "drive_pkl"
sys.path.insert(0, str(FIX))
import make_pickles as mp  # noqa: E402

FORMS = {
    "raw_dataframe": ("raw", "raw+icp"),
    "torch_ready_dataframe": ("windows", "torch_ready"),
    "slip_dataset_all": ("windows", "slip_dataset_all"),
}
MAKE = {**mp.FRAMES, **mp.TYPED}
FORM_OF = {**FORMS, "raw_dataframe_typed": FORMS["raw_dataframe"]}


def _same(got: pd.DataFrame, expected: pd.DataFrame) -> None:
    assert list(got.columns) == list(expected.columns)
    assert got.shape == expected.shape
    assert [str(x) for x in got.index] == [str(x) for x in expected.index]
    for c in expected.columns:  # text stays text (object or str dtype, by pandas version), numbers numbers
        a, b = got[c].to_numpy(), expected[c].to_numpy()
        if expected[c].dtype.kind == "f":
            np.testing.assert_array_equal(a.astype(float), b)
        else:
            assert [str(x) for x in a] == [str(x) for x in b], c


@pytest.mark.parametrize("pickled", sorted(FIX.glob("*.pkl.gz")), ids=lambda p: p.name)
def test_pickles_of_older_pandas_read_as_the_frames_they_hold(pickled, tmp_path):
    name = pickled.name.split(".pandas")[0]
    plain = tmp_path / f"{name}.pkl"  # as DRIVE publishes them: uncompressed
    plain.write_bytes(gzip.decompress(pickled.read_bytes()))
    for path in (plain, pickled):
        got = read_frame(path)
        _same(got, MAKE[name]())
        assert detect_form(got, path) == FORM_OF[name]


def test_the_fixtures_cover_every_pandas_minor_version_from_1_5_to_3_0():
    tags = {(p.name.split(".pandas")[0], p.name.split(".pandas")[1][:3]) for p in FIX.glob("*.pkl.gz")}
    assert {t for t in tags if t[0] in FORMS} >= {(n, v) for n in FORMS for v in ("1.5", "2.2")}
    assert {v for n, v in tags if n == "raw_dataframe"} == {"1.5", "2.0", "2.1", "2.2", "2.3", "3.0"}
    assert {v for n, v in tags if n == "raw_dataframe_typed"} == {"1.5", "2.3", "3.0"}


DRIVE_PKL = FIX / "drive" / "raw_dataframe.gravel_test_wg.pkl"


def test_a_pickle_drive_published_with_pandas_partial_blocks_reads_as_its_raw_form(tmp_path):
    """DRIVE's own raw_dataframe.pkl (pandas < 1.5: every block rebuilt through functools.partial around
    pandas' new_block) reads as the two text rows it holds, plain and gzip-compressed."""
    from skidbench.pipeline.sources.drive_files import typed_raw_frame

    data = DRIVE_PKL.read_bytes()
    assert b"functools" in data and b"partial" in data and b"new_block" in data  # the layout under test
    (tmp_path / "raw_dataframe.pkl.gz").write_bytes(gzip.compress(data))
    for path in (DRIVE_PKL, tmp_path / "raw_dataframe.pkl.gz"):
        df = read_frame(path)
        assert df.shape == (2, 22) and detect_form(df, path) == ("raw", "raw+icp")
        assert str(df["ros_time"].iloc[1]) == "1720021356273697920" and df["calib_state"].iloc[1] == "idle"
    typed = typed_raw_frame(df, DRIVE_PKL, ["ros_time", "cmd_vel_x", "meas_left_vel", "icp_quat_w"])
    assert len(typed) == 1 and typed["icp_quat_w"].iloc[0] == 1.0  # the zero placeholder row dropped


NEW_BLOCK = ("pandas.core.internals.blocks", "new_block")
#: partials a pickle may hold, by what they wrap: refused unless around pandas' block constructor with ndim
PARTIALS = {
    "DataFrame": ((pd.DataFrame, {"a": [1]}), {}, r"around pandas(\.core\.frame)?\.DataFrame, not one of"),
    "ndarray": ((np.ndarray,), {}, r"around numpy\.ndarray, not one of pandas' block constructors"),
    "bound args": ((NEW_BLOCK, np.zeros((1, 2))), {"ndim": 2}, r"arguments pandas never binds"),
    "other keyword": ((NEW_BLOCK,), {"ndim": 2, "refs": None}, r"keywords \['ndim', 'refs'\]"),
    "ndim 7": ((NEW_BLOCK,), {"ndim": 7}, r"arguments pandas never binds"),
}


@pytest.mark.parametrize("case", sorted(PARTIALS))
def test_functools_partial_is_admitted_only_around_pandas_block_constructors(case, tmp_path):
    from pandas.core.internals import blocks

    (func, *args), keywords, why = PARTIALS[case]
    func = blocks.new_block if func == NEW_BLOCK else func
    path = tmp_path / "raw_dataframe.pkl"
    path.write_bytes(pickle.dumps(functools.partial(func, *args, **keywords), protocol=4))
    with pytest.raises(
        UnsafePickleError, match=r"raw_dataframe\.pkl: refused as unsafe: the pickle calls"
    ) as e:
        read_frame(path)
    assert re.search(why, str(e.value)) and "\n" not in str(e.value)


def test_a_partial_around_a_refused_global_is_refused_at_that_global(tmp_path):
    path = tmp_path / "raw_dataframe.pkl"
    path.write_bytes(pickle.dumps(functools.partial(print, "pwned")))
    with pytest.raises(UnsafePickleError, match=r"the pickle calls builtins\.print, which a pandas"):
        read_frame(path)


#: pandas' data types besides float and text, one column (or index) each: read, never refused as unsafe
DATA_TYPES = {
    "nullable text": lambda: pd.array(["calib", None, "idle"], dtype="string"),
    "nullable int": lambda: pd.array([1, None, 3], dtype="Int64"),
    "nullable uint8": lambda: pd.array([1, None, 3], dtype="UInt8"),
    "nullable float": lambda: pd.array([0.5, None, 1.5], dtype="Float64"),
    "nullable bool": lambda: pd.array([True, None, False], dtype="boolean"),
    "category": lambda: pd.Categorical(["calib", "idle", "calib"]),
    "datetime": lambda: pd.to_datetime([1, 2, 3], unit="s"),
    "datetime UTC": lambda: pd.to_datetime([1, 2, 3], unit="s", utc=True),
    "timedelta": lambda: pd.to_timedelta([1, 2, 3], unit="s"),
    "int32": lambda: np.array([1, 2, 3], dtype=np.int32),
    "bool": lambda: np.array([True, False, True]),
}  # fmt: skip


@pytest.mark.parametrize("kind", sorted(DATA_TYPES))
def test_pandas_data_types_are_read_not_refused(kind, tmp_path):
    df = pd.DataFrame({"cmd_vel_x": [0.5, 0.4, 0.3], "c": DATA_TYPES[kind]()})
    for index in (
        None,
        pd.DatetimeIndex(pd.to_datetime([1, 2, 3], unit="s", utc=True), name="t"),
        pd.TimedeltaIndex(pd.to_timedelta([1, 2, 3], unit="s")),
        pd.CategoricalIndex(list("abc")),
    ):
        framed = df if index is None else df.set_axis(index)
        for protocol in range(2, pickle.HIGHEST_PROTOCOL + 1):
            path = tmp_path / f"p{protocol}.pkl"
            path.write_bytes(pickle.dumps(framed, protocol=protocol))
            pd.testing.assert_frame_equal(read_frame(path), framed)
    columns = pd.MultiIndex.from_tuples([("cmd", "v"), ("cmd", "w")])  # a MultiIndex of columns
    pd.DataFrame(np.ones((2, 2)), columns=columns).to_pickle(tmp_path / "m.pkl")
    assert read_frame(tmp_path / "m.pkl").columns.equals(columns)


def test_a_raw_frame_of_nullable_types_reads_as_the_same_numbers(tmp_path):
    """The raw frame in pandas' nullable types (pandas 2.3.3's pickle and the installed pandas'): the
    columns the reader needs are the same numbers as DRIVE's text storage gives, placeholder row dropped."""
    from skidbench.pipeline.sources.drive_files import typed_raw_frame

    needed = [c for c in mp.RAW_COLUMNS if c not in ("joy_switch", "calib_state", "icp_index")]
    want = typed_raw_frame(mp.raw_frame(), Path("raw.pkl"), needed)[needed].to_numpy(float)
    mp.typed_raw_frame().to_pickle(tmp_path / "raw_dataframe.pkl")
    for path in (FIX / "raw_dataframe_typed.pandas2.3.3.pkl.gz", tmp_path / "raw_dataframe.pkl"):
        got = typed_raw_frame(read_frame(path), path, needed)
        np.testing.assert_array_equal(got[needed].to_numpy(float), want)
        assert list(got["calib_state"].astype(str)) == ["idle"] * 3 + ["calib"] * 5


@pytest.mark.parametrize("protocol", range(2, pickle.HIGHEST_PROTOCOL + 1))
def test_pickles_of_the_installed_pandas_read_back(protocol, tmp_path):
    for name, make in mp.FRAMES.items():
        path = tmp_path / f"{name}.pkl"
        path.write_bytes(pickle.dumps(make(), protocol=protocol))
        _same(read_frame(path), make())
        # and as text columns of the installed pandas' own string dtype
    text = mp.raw_frame().astype("str")
    text.to_pickle(tmp_path / "t.pkl")
    _same(read_frame(tmp_path / "t.pkl"), text)


def _global_pickle(module: str, name: str) -> bytes:
    """A protocol-2 pickle that looks up ``module.name`` and calls it with one string argument."""
    return b"\x80\x02c" + module.encode() + b"\n" + name.encode() + b"\nX\x04\x00\x00\x00trueq\x00\x85R."


@pytest.mark.parametrize(
    ("module", "name"),
    [
        ("posix", "system"),
        ("builtins", "eval"),
        ("pandas", "read_csv"),
        ("pandas.core.frame", "DataFrame.eval"),
        ("this", "d"),
    ],  # fmt: skip
)
def test_a_pickle_naming_anything_else_is_refused_before_it_is_imported(module, name, tmp_path):
    path = tmp_path / "raw_dataframe.pkl"
    data = _global_pickle(module, name)
    path.write_bytes(data)
    fresh = "this" not in sys.modules
    with pytest.raises(
        UnsafePickleError, match=f"raw_dataframe.pkl: refused as unsafe: the pickle calls {module}"
    ):
        read_frame(path)
    if fresh:  # the refused module was never imported (importing `this` prints the Zen of Python)
        assert "this" not in sys.modules
    assert (module, name) not in ALLOWED_GLOBALS


def test_a_damaged_or_foreign_pickle_is_one_line(tmp_path):
    good = pickle.dumps(mp.windows_frame())
    (tmp_path / "cut.pkl").write_bytes(good[: len(good) // 2])
    with pytest.raises(SourceError, match=r"cut\.pkl: not a readable pandas pickle") as e:
        read_frame(tmp_path / "cut.pkl")
    assert "\n" not in str(e.value)
    (tmp_path / "empty.pkl").write_bytes(b"")  # DRIVE's data_raw.pkl files are empty
    with pytest.raises(SourceError, match=r"empty\.pkl: an empty file \(0 bytes\)"):
        read_frame(tmp_path / "empty.pkl")
    (tmp_path / "lfs.pkl").write_text("version https://git-lfs.github.com/spec/v1\noid sha256:00\nsize 9\n")
    with pytest.raises(SourceError, match=r"lfs\.pkl: a Git LFS pointer, not the file itself; run `git lfs"):
        read_frame(tmp_path / "lfs.pkl")
    (tmp_path / "list.pkl").write_bytes(pickle.dumps([1.0, 2.0]))
    with pytest.raises(SourceError, match=r"list\.pkl: the pickle holds a list, not a DRIVE dataframe"):
        read_frame(tmp_path / "list.pkl")


def test_a_pickle_extracts_the_same_sequences_as_its_parquet(tmp_path):
    from omegaconf import OmegaConf
    from test_sources_drive_synthetic import drive_like_frame

    from skidbench.pipeline.core.robot import load_robot
    from skidbench.pipeline.sources.contract import settings_from
    from skidbench.pipeline.sources.drive_df import DriveSettings, _read_file

    df = drive_like_frame([(0.5, 0.0), (0.4, 0.3), (0.6, -0.2), (0.3, 0.1), (0.5, 0.4)])[0]
    df.to_parquet(tmp_path / "w.parquet")
    df.to_pickle(tmp_path / "torch_ready_dataframe.pkl")
    df.convert_dtypes().to_pickle(tmp_path / "nullable.pkl")  # Float64 columns: the same sequences
    conf = OmegaConf.load(Path(__file__).parents[1] / "conf" / "source" / "drive_df.yaml")
    src = settings_from(DriveSettings, OmegaConf.to_container(conf), "drive_df")
    a = _read_file(tmp_path / "w.parquet", src, load_robot("husky"), "h")
    for other in ("torch_ready_dataframe.pkl", "nullable.pkl"):
        b = _read_file(tmp_path / other, src, load_robot("husky"), "h")
        assert [s.name for s in a[2]] == [s.name for s in b[2]] and a[3] == b[3]
        for sa, sb in zip(a[2], b[2], strict=True):
            for k in sa.tables.present():
                pd.testing.assert_frame_equal(sa.tables.present()[k], sb.tables.present()[k])
