"""DRIVE's own files: pandas pickles (``raw_dataframe.pkl``, ``torch_ready_dataframe.pkl``,
``slip_dataset_all.pkl``) read through the restricted unpickler, as pandas 1.5, 2.2 and the installed one
write them; anything a dataframe does not hold is refused as unsafe, before it is imported or called."""

from __future__ import annotations

import gzip
import pickle
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from skidbench.pipeline.errors import SourceError
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


def test_the_fixtures_cover_two_pandas_versions_of_every_form():
    tags = {(p.name.split(".pandas")[0], p.name.split(".pandas")[1][:3]) for p in FIX.glob("*.pkl.gz")}
    assert {t for t in tags if t[0] in FORMS} == {(n, v) for n in FORMS for v in ("1.5", "2.2")}
    assert ("raw_dataframe_typed", "2.3") in tags


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
    (tmp_path / "list.pkl").write_bytes(pickle.dumps([1.0, 2.0]))
    with pytest.raises(SourceError, match=r"list\.pkl: the pickle holds a list, not a DRIVE dataframe"):
        read_frame(tmp_path / "list.pkl")


def test_a_pickle_extracts_the_same_sequences_as_its_parquet(tmp_path):
    from omegaconf import OmegaConf
    from test_sources_drive_synthetic import drive_like_frame

    from skidbench.pipeline.robot import load_robot
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
