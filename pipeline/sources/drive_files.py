"""DRIVE's files as they come (``source=drive_df``): where they are, which form they hold, and reading them.

**Containers.** A file is read by its content, never its suffix: Parquet (``PAR1``), or a pandas pickle
(what DRIVE publishes: ``raw_dataframe.pkl``, ``torch_ready_dataframe.pkl``, ``slip_dataset_all.pkl``),
plain or gzip/bz2/xz-compressed. A pickle can run any code it names, so it is read by a restricted
unpickler (:class:`DataFrameUnpickler`, the "restricting globals" recipe of Python's :mod:`pickle` docs
on top of pandas' own compatibility unpickler): it admits only the (module, name) pairs in
:data:`ALLOWED_GLOBALS`, the pandas and numpy types a dataframe of numbers and text holds as pandas
1.x-3.x and numpy 1.x-2.x write it (float, int, bool and text columns, pandas' nullable ones and pd.NA,
categories, datetimes with a UTC offset, timedeltas, their indexes and a MultiIndex), and the calls pandas
itself makes to rebuild them. pandas 1.3-1.4 pickle each block as ``functools.partial(new_block,
ndim=n)(values, placement)`` (most of DRIVE's published pickles): ``functools.partial`` is admitted only
around pandas' own block constructors (:data:`BLOCK_CONSTRUCTORS`) with ``ndim`` its one keyword
(:class:`_BlockPartial`). Anything else is refused in one line as unsafe, before it is called.

**Forms.** :func:`detect_form` picks the form from the columns: ``windows`` (every window version DRIVE
wrote: the 578-column ``torch_ready``, the 1218-column ``slip_dataset_all``, any newer one with more
columns) or ``raw`` (the 20 Hz time series, with or without ICP, voltage and current).

**Text storage.** DRIVE's logger stores a raw recording as one array of text: every column of the
published raw files is text (``'1721336326440222197'``, ``'0.0'``, ``'calib'``), and its first row is the
zero-initialised placeholder (``ros_time`` 0, ``calib_state`` ``'0.0'``). :func:`typed_raw_frame` undoes
that once, at the cause: a text column whose values are all numbers is a number column (no warning: it is
how DRIVE stores them), the placeholder row is dropped (one line), and only a value that really is not a
number in a needed column is reported.
"""

from __future__ import annotations

import bz2
import datetime
import gzip
import importlib.util
import io
import logging
import lzma
import pickle
from pathlib import Path

import numpy as np
import pandas as pd

from skidbench.pipeline.core.errors import ConfigError, SourceError

log = logging.getLogger("skidbench.pipeline.sources.drive_df")

#: the suffixes of the files ``source=drive_df`` reads (the folder listing in an error names these)
DATA_SUFFIXES = (".parquet", ".pkl", ".pickle", ".pkl.gz", ".pkl.bz2", ".pkl.xz")

# -- the restricted unpickler -------------------------------------------------------------------------
_NUMPY = {
    ("numpy", "dtype"), ("numpy", "ndarray"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
}  # fmt: skip
_PANDAS = {
    ("pandas.core.frame", "DataFrame"), ("pandas", "DataFrame"),
    ("pandas.core.series", "Series"), ("pandas", "Series"),
    ("pandas.core.internals.managers", "BlockManager"),
    ("pandas.core.internals.managers", "SingleBlockManager"),
    ("pandas._libs.internals", "_unpickle_block"),
    ("pandas._libs.arrays", "__pyx_unpickle_NDArrayBacked"),
    ("pandas.core.indexes.base", "_new_Index"),
    ("pandas.core.indexes.base", "Index"), ("pandas", "Index"),
    ("pandas.core.indexes.range", "RangeIndex"), ("pandas", "RangeIndex"),
    ("pandas.core.arrays.datetimes", "DatetimeArray"), ("pandas.arrays", "DatetimeArray"),
    ("pandas.core.dtypes.dtypes", "DatetimeTZDtype"),
    ("pandas._libs.tslibs.timestamps", "_unpickle_timestamp"),
    ("pandas._libs.tslibs.nattype", "_nat_unpickle"),
    ("pandas.core.arrays.string_", "StringDtype"), ("pandas", "StringDtype"),
    ("pandas.core.arrays.string_", "StringArray"), ("pandas.arrays", "StringArray"),
    ("pandas.core.arrays.string_arrow", "ArrowStringArray"), ("pandas.arrays", "ArrowStringArray"),
    # pandas 3 keeps text columns in Arrow arrays: their pickles rebuild them with these
    ("pyarrow.lib", "_restore_array"), ("pyarrow.lib", "py_buffer"), ("pyarrow.lib", "type_for_alias"),
}  # fmt: skip
#: pandas' other data types (nullable numbers and booleans, pd.NA, categories, times and their indexes, a
#: MultiIndex of columns) by the names pandas 1.5-2.x and 3.x write: a lab's own dataframe may hold them
#: (``convert_dtypes()``, a time index), and refusing them as unsafe would name the wrong reason
_PANDAS_TYPES = {
    ("pandas._libs.missing", "NA"), ("pandas", "NA"),
    *{(m, n) for m, names in {
        "pandas.core.arrays.integer": ("IntegerArray", *(f"{u}Int{b}Dtype" for u in ("", "U")
                                                          for b in (8, 16, 32, 64))),
        "pandas.core.arrays.floating": ("FloatingArray", "Float32Dtype", "Float64Dtype"),
        "pandas.core.arrays.boolean": ("BooleanArray", "BooleanDtype"),
        "pandas.core.arrays.categorical": ("Categorical",),
        "pandas.core.dtypes.dtypes": ("CategoricalDtype",),
        "pandas.core.arrays.timedeltas": ("TimedeltaArray",),
        "pandas.core.indexes.category": ("CategoricalIndex",),
        "pandas.core.indexes.datetimes": ("DatetimeIndex", "_new_DatetimeIndex"),
        "pandas.core.indexes.timedeltas": ("TimedeltaIndex", "_new_TimedeltaIndex"),
        "pandas.core.indexes.multi": ("MultiIndex",),
    }.items() for n in names},
    *{("pandas", n) for n in ("Categorical", "CategoricalDtype", "CategoricalIndex", "DatetimeIndex",
                              "TimedeltaIndex", "MultiIndex", "DatetimeTZDtype", "BooleanDtype",
                              "Float32Dtype", "Float64Dtype",
                              *(f"{u}Int{b}Dtype" for u in ("", "U") for b in (8, 16, 32, 64)))},
    *{("pandas.arrays", n) for n in ("IntegerArray", "FloatingArray", "BooleanArray", "Categorical",
                                     "TimedeltaArray")},
    ("pandas._libs.tslibs.timedeltas", "_timedelta_unpickle"),
    ("datetime", "timezone"), ("datetime", "timedelta"),  # a UTC-offset time zone (pandas 2-3's UTC)
    ("pytz", "_UTC"),  # pandas 1.x's UTC
}  # fmt: skip
#: pandas' block constructors, the one thing a pickle may wrap in ``functools.partial`` (pandas 1.3-1.4's
#: ``SharedBlock.__reduce__``: ``partial(new_block, ndim=n)``; pandas' unpickler maps ``new_block`` to
#: ``_unpickle_block``, which takes the same arguments)
BLOCK_CONSTRUCTORS = frozenset({
    ("pandas.core.internals.blocks", "new_block"), ("pandas._libs.internals", "_unpickle_block"),
})  # fmt: skip
_PYTHON = {
    ("builtins", "slice"), ("__builtin__", "slice"),
    ("builtins", "bytearray"), ("__builtin__", "bytearray"),
    ("_codecs", "encode"),  # how protocol 2 writes bytes
}  # fmt: skip
#: every global a DRIVE dataframe pickle may name (after pandas' renames of legacy names), and
#: ``functools.partial`` as :class:`_BlockPartial`
ALLOWED_GLOBALS = frozenset(_NUMPY | _PANDAS | _PANDAS_TYPES | _PYTHON | BLOCK_CONSTRUCTORS)
_PARTIAL = ("functools", "partial")


class UnsafePickleError(SourceError):
    """A pickle that names a global a dataframe of numbers and text does not hold."""


def _unsafe(path: Path, what: str) -> UnsafePickleError:
    return UnsafePickleError(
        f"{path}: refused as unsafe: the pickle calls {what} (unpickling it could run code); convert the "
        "file to Parquet (pandas.read_pickle(f).to_parquet(...)) where you trust its origin"
    )


class _BlockPartial:
    """``functools.partial`` while a dataframe is unpickled: pandas 1.3-1.4's ``partial(new_block,
    ndim=n)`` and nothing else. A pickle builds a partial as ``partial(func)``, then sets its state
    ``(func, args, keywords, dict)``; each step is checked before anything is called: ``func`` one of
    pandas' block constructors (``constructors``: the very objects :data:`BLOCK_CONSTRUCTORS` names), no
    bound arguments, ``ndim`` (1 or 2) the one keyword. Called with (values, placement), it builds the
    block."""

    path: Path = Path("?")
    constructors: tuple = ()

    def __init__(self, func, *args, **keywords) -> None:
        self._set(func, args, keywords, None)

    def __setstate__(self, state) -> None:
        if not (isinstance(state, tuple) and len(state) == 4):
            raise _unsafe(
                self.path, "functools.partial with a state that is not (func, args, keywords, dict)"
            )
        self._set(*state)

    def _set(self, func, args, keywords, extra) -> None:
        if not any(func is f for f in self.constructors):
            what = f"{getattr(func, '__module__', '?')}.{getattr(func, '__qualname__', type(func).__name__)}"
            raise _unsafe(
                self.path, f"functools.partial around {what}, not one of pandas' block constructors"
            )
        keywords = dict(keywords or {})
        if args or extra or set(keywords) - {"ndim"} or keywords.get("ndim", 2) not in (1, 2):
            raise _unsafe(
                self.path,
                f"functools.partial around pandas' block constructor with arguments pandas never binds "
                f"(args {args!r}, keywords {sorted(keywords)})",
            )
        self.func, self.ndim = func, keywords.get("ndim")

    def __call__(self, values, placement):
        if self.ndim is None:
            raise _unsafe(self.path, "pandas' block constructor through functools.partial without its ndim")
        return self.func(values, placement, ndim=self.ndim)


def _compat_unpickler() -> type:
    """pandas' own unpickler (legacy names and layouts of older pandas), or the standard one."""
    try:
        from pandas.compat.pickle_compat import Unpickler
    except ImportError:  # pragma: no cover - every pandas this package supports has it
        return pickle.Unpickler
    return Unpickler


class DataFrameUnpickler(_compat_unpickler()):
    """Unpickles a pandas dataframe and nothing else: ``find_class`` admits only :data:`ALLOWED_GLOBALS`
    (legacy names mapped by pandas first); any other global raises :class:`UnsafePickleError` before it
    is looked up, so nothing it names is imported or called."""

    path: Path = Path("?")

    def find_class(self, module: str, name: str):
        try:
            from pandas.compat.pickle_compat import _class_locations_map as renames
        except ImportError:  # pragma: no cover
            renames = {}
        key = renames.get((module, name), (module, name))
        if key == _PARTIAL:  # pandas 1.3-1.4's blocks: checked as the pickle builds it
            return type("BlockPartial", (_BlockPartial,), {"path": self.path, "constructors": self._blocks()})
        if key not in ALLOWED_GLOBALS:
            raise _unsafe(
                self.path, f"{module}.{name}, which a pandas dataframe of numbers and text does not hold"
            )
        if key == ("pytz", "_UTC") and importlib.util.find_spec("pytz") is None:
            return _utc  # pandas 1.x's UTC; pandas 3 no longer installs pytz
        if np.lib.NumpyVersion(np.__version__) >= "2.0.0" and key[0].startswith("numpy.core."):
            key = ("numpy._core." + key[0].removeprefix("numpy.core."), key[1])  # numpy 1.x's names
        return super().find_class(*key)

    def _blocks(self) -> tuple:
        """The installed pandas' block constructors, as this unpickler resolves their names."""
        found = []
        for key in sorted(BLOCK_CONSTRUCTORS):
            try:
                found.append(self.find_class(*key))
            except (AttributeError, ImportError):  # a pandas without one of the names
                continue
        return tuple(found)


def _utc() -> datetime.tzinfo:
    """What ``pytz._UTC()`` unpickles to where pytz is not installed: the same UTC, the standard library's."""
    return datetime.UTC


_MAGIC = {b"\x1f\x8b": gzip.open, b"BZh": bz2.open, b"\xfd7zXZ": lzma.open}


def read_pickle_frame(path: Path) -> pd.DataFrame:
    """A pandas pickle (plain or gzip/bz2/xz) through :class:`DataFrameUnpickler`; SourceError unless it
    holds one DataFrame."""
    with open(path, "rb") as fh:
        head = fh.read(6)
    opener = next((f for magic, f in _MAGIC.items() if head.startswith(magic)), open)
    try:
        with opener(path, "rb") as fh:
            unpickler = DataFrameUnpickler(io.BufferedReader(fh) if opener is not open else fh)
            unpickler.path = path
            obj = unpickler.load()
    except UnsafePickleError:
        raise
    except Exception as exc:  # a truncated or damaged pickle fails anywhere inside the unpickler
        raise SourceError(f"{path}: not a readable pandas pickle ({type(exc).__name__}: {exc})") from exc
    if not isinstance(obj, pd.DataFrame):
        raise SourceError(f"{path}: the pickle holds a {type(obj).__name__}, not a DRIVE dataframe")
    return obj


def read_frame(path: Path) -> pd.DataFrame:
    """A DRIVE file (Parquet or pandas pickle, by content) as a DataFrame; SourceError in one line."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(32)
    except FileNotFoundError as exc:
        raise SourceError(f"{path}: no such file; set source.root and source.file") from exc
    except IsADirectoryError as exc:
        raise SourceError(f"{path}: a folder, not a DRIVE file; set source.file") from exc
    if not head:
        raise SourceError(f"{path}: an empty file (0 bytes), not a DRIVE file; copy or download it again")
    if head.startswith(b"version https://git-lfs"):  # a clone without `git lfs pull`
        raise SourceError(f"{path}: a Git LFS pointer, not the file itself; run `git lfs pull` where it is")
    if head[:1] == b"\x80" or any(head.startswith(m) for m in _MAGIC):
        return read_pickle_frame(path)
    try:
        return pd.read_parquet(path)
    except Exception as exc:  # pyarrow raises several types for a corrupt file
        raise SourceError(
            f"{path}: not a readable Parquet file or pandas pickle ({type(exc).__name__}: {exc})"
        ) from exc


# -- where the files are ------------------------------------------------------------------------------
def data_files(root: Path) -> list[str]:
    """The DRIVE-readable files directly in ``root`` (by suffix), sorted."""
    return sorted(p.name for p in root.iterdir() if p.is_file() and p.name.endswith(DATA_SUFFIXES))


def check_paths(root: Path, files: list[str]) -> list[Path]:
    """``root/<file>`` for every file, or one SourceError naming what is missing and what is there."""
    if not root.exists():
        raise SourceError(
            f"source.root={root}: no such folder; set source.root to the folder of the DRIVE files"
        )
    if not root.is_dir():
        raise SourceError(
            f"source.root={root}: not a folder; set source.root to the folder of the DRIVE files"
        )
    paths = [root / f for f in files]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        there = data_files(root)
        held = (
            f"it holds {', '.join(there[:8])}{' ...' if len(there) > 8 else ''}; "
            "set source.file=<one of them>"
            if there
            else f"{root} holds no DRIVE file ({', '.join(DATA_SUFFIXES)})"
        )
        raise SourceError(f"{missing[0]}: no such file ({held})")
    return paths


# -- forms --------------------------------------------------------------------------------------------
WINDOW = 40
#: the 40-sample blocks every window version holds, and the extra ones of ``slip_dataset_all``
WINDOW_BLOCKS = ("cmd_left", "cmd_right", "left_wheel_vel", "right_wheel_vel", "icp_x", "icp_y", "icp_yaw")
SLIP_BLOCKS = ("icp_vel_x", "idd_vel_x", "body_vel_disturption_x", "icp_interpolated_x")
RAW_COLUMNS = ("ros_time", "cmd_vel_x", "cmd_vel_omega", "meas_left_vel", "meas_right_vel", "calib_step")
FORMS = ("auto", "windows", "raw")


def detect_form(df: pd.DataFrame, path: Path) -> tuple[str, str]:
    """``(form, version)`` from the columns: ``("windows", "torch_ready" | "slip_dataset_all" |
    "windows+<n> columns")`` or ``("raw", "raw" | "raw+icp" | "raw+icp+power")``; SourceError otherwise
    (a frame with encoders but no commands says so)."""
    cols = set(map(str, df.columns))
    if "cmd_left_0" in cols or "left_wheel_vel_0" in cols:
        if "cmd_left_0" not in cols:
            raise SourceError(
                f"{path}: no commands: the window form's cmd_left_0..39 and cmd_right_0..39 are absent "
                "(the wheels and ICP are there); nothing is driven by a recorded command"
            )
        if all(f"{b}_0" in cols for b in SLIP_BLOCKS):
            return "windows", "slip_dataset_all"
        return "windows", "torch_ready" if len(cols) == 578 else f"windows+{len(cols)} columns"
    if "meas_left_vel" in cols and not {"cmd_vel_x", "cmd_vel_omega"} <= cols:
        raise SourceError(
            f"{path}: no commands: the raw form's cmd_vel_x / cmd_vel_omega are absent (the encoders "
            "meas_left_vel, meas_right_vel are there); nothing is driven by a recorded command"
        )
    if {"cmd_vel_x", "meas_left_vel"} <= cols:
        version = "raw+icp" if "icp_pos_x" in cols else "raw"
        return "raw", version + ("+power" if "left_wheel_current" in cols else "")
    raise SourceError(
        f"{path}: not a DRIVE dataframe: neither window columns (cmd_left_0, left_wheel_vel_0, ...) nor raw "
        f"columns (cmd_vel_x, meas_left_vel, ...); it has {len(cols)} columns, e.g. {sorted(cols)[:5]}"
    )


def check_form(asked: str, form: str, version: str, path: Path) -> None:
    """``source.form``: ``auto`` or the form the columns hold."""
    if asked not in FORMS:
        raise ConfigError(f"source.form={asked!r}: expected auto, windows or raw")
    if asked != "auto" and asked != form:
        raise SourceError(f"{path}: source.form={asked} but the columns are DRIVE's {version} form")


def _is_text(s: pd.Series) -> bool:
    return s.dtype == object or str(s.dtype) in ("string", "str") or isinstance(s.dtype, pd.StringDtype)


def typed_raw_frame(df: pd.DataFrame, path: Path, needed: list[str]) -> pd.DataFrame:
    """A raw frame as DRIVE meant it (module docstring, "Text storage"): the ``needed`` columns as numbers
    (stored as text or not: no warning, it is how DRIVE stores them), DRIVE's zero-initialised
    placeholder row (every needed value 0) dropped with one line, and rows whose needed values are not
    numbers dropped with one warning naming the columns and counts. Other columns are left as they are
    (``calib_state`` is text)."""
    out = df.copy()
    bad: dict[str, int] = {}
    for c in needed:
        num = pd.to_numeric(out[c], errors="coerce")
        if _is_text(out[c]):
            blank = out[c].isna() | (out[c].astype(str).str.strip() == "")
            if n_bad := int((num.isna() & ~blank).sum()):
                bad[c] = n_bad
        out[c] = num.astype(float)
    placeholder = _placeholder_rows(out, needed)
    if placeholder.any():
        log.info(
            "%s: dropped DRIVE's zero-initialised placeholder row(s) (%d: ros_time and every value 0)",
            path.name,
            int(placeholder.sum()),
        )
        out = out[~placeholder]
    missing = out[needed].isna().any(axis=1)
    if missing.any():
        where = ", ".join(f"{c}: {n}" for c, n in bad.items()) or "empty values"
        log.warning(
            "%s: dropped %d row(s) whose needed values are not numbers (%s)", path, int(missing.sum()), where
        )
        out = out[~missing]
    return out


def _placeholder_rows(df: pd.DataFrame, needed: list[str]) -> np.ndarray:
    """Rows with ``ros_time`` 0 whose every needed number is 0 (DRIVE's logger's first row)."""
    if "ros_time" not in df.columns:
        return np.zeros(len(df), dtype=bool)
    vals = df[[c for c in needed if c in df.columns]].to_numpy(dtype=float)
    return np.all(np.nan_to_num(vals, nan=1.0) == 0.0, axis=1)


#: a ROS time since 1970 of the years 2000-2100 in each unit: how a raw file's ``ros_time`` unit is told
_EPOCH_S = (946_684_800.0, 4_102_444_800.0)
_UNITS = {"s": 1.0, "ms": 1e3, "us": 1e6, "ns": 1e9}


def ros_time_ns(t: np.ndarray, path: Path) -> np.ndarray:
    """``ros_time`` (valid rows, float) in nanoseconds, DRIVE's unit. A clock of the years 2000-2100 in
    seconds, milliseconds or microseconds (a lab's converted file, a datetime column of another
    resolution) is converted, with one warning naming the unit; a clock that steps by under 1 per row and
    is no such date is refused in one line (a nanosecond clock never does)."""
    t = np.asarray(t, dtype=float)
    mid = float(np.median(t)) if t.size else 0.0
    unit = next((u for u, k in _UNITS.items() if _EPOCH_S[0] * k <= mid <= _EPOCH_S[1] * k), None)
    if unit is not None and unit != "ns":
        log.warning(
            "%s: ros_time is in %s (median %.6g: a date of %s in %s, not in ns); converted to ns",
            path.name, unit, mid, pd.Timestamp(mid / _UNITS[unit], unit="s").year, unit,
        )  # fmt: skip
        return t * (1e9 / _UNITS[unit])
    steps = np.diff(t)
    steps = steps[steps > 0]
    if unit is None and steps.size and float(np.median(steps)) < 1.0:
        raise SourceError(
            f"{path}: ros_time steps by {float(np.median(steps)):.3g} per row (median): not nanoseconds, "
            "DRIVE's unit, and not a date in s, ms or us either; give ros_time in ns"
        )
    return t
