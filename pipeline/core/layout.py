"""Where every stage reads and writes: one output root (``out_root``, default ``outputs/``, env
``SKIDBENCH_OUT``), one folder per dataset under it, one subfolder per stage.

    <out_root>/mlflow.db, mlartifacts/           MLflow tracking store (shared by all datasets)
    <out_root>/<dataset>/dataset.json            the dataset's identity (pipeline/datasets/identity.py)
    <out_root>/<dataset>/raw/                    simulate output: manifest.json, bags/
    <out_root>/<dataset>/extracted/<seq>/        extract output: <topic_key>.parquet, manifest
    <out_root>/<dataset>/groundtruth/            <seq>.tum, <seq>.json, loop_closure.json
    <out_root>/<dataset>/splits/<terrain>/<split>/<seq>.parquet, card.md
    <out_root>/<dataset>/calibration/<terrain>.json   calibrate output: effective wheel radius, track width
    <out_root>/<dataset>/fits/<model>/<terrain>[.<inputs>].json
    <out_root>/<dataset>/eval/, reports/, discovery/

Which terrains and sequences a stage works on comes from the current manifest (``raw/manifest.json``),
never from the folders that happen to exist: :meth:`Layout.split_files` lists the split files of the
manifest's sequences, and :func:`prune_stale` removes every output of a sequence (or terrain) the
manifest no longer holds.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import OmegaConf

from skidbench.pipeline.core.errors import ConfigError

if TYPE_CHECKING:
    from skidbench.pipeline.core.manifest import Manifest

DEFAULT_OUT_ROOT = "outputs"
#: the input protocols (config key ``inputs``): what drives every model, pipeline/core/protocol.py
PROTOCOLS = ("commanded", "response", "measured", "state")


@dataclass(frozen=True)
class CommonSettings:
    """The root keys every stage's config has: their schema and defaults (``conf/common.yaml`` lists it,
    ``/schema/root/common``; ``pipeline/cli/config_schema.py``). Read whole with :func:`root_from_cfg`."""

    out_root: str = "${oc.env:SKIDBENCH_OUT,outputs}"  # every generated file lives under here
    dataset: str = "${source.dataset}"  # the folder under out_root for this dataset
    seed: int = field(default=0, metadata={"lo": 0})
    # what drives every model (pipeline/core/protocol.py): commanded (the paper's: commanded wheel rates and
    # their derivatives), response (the commands through the wheel response `calibrate` identified per
    # terrain from the Train encoders), measured (the encoders' rates: an oracle), state (each window from
    # the robot's state, for dynamics models). Every model of a run gets the same inputs.
    inputs: str = field(
        default="commanded", metadata={"choices": PROTOCOLS, "what": "the model input protocol"}
    )


def root_from_cfg(cfg: Any, cls: type) -> Any:
    """The root keys of a composed config that dataclass ``cls`` declares (a stage's schema stored at the
    root, ``pipeline/cli/config_schema.py`` ``ROOTS``), read once into a ``cls``; a key the config lacks
    (a config composed for another stage) takes its default."""
    register_resolvers()
    values = {}
    for f in fields(cls):
        if f.name in cfg:
            node = cfg[f.name]
            values[f.name] = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
    return cls(**values)


def default_out_root() -> Path:
    return Path(os.environ.get("SKIDBENCH_OUT", DEFAULT_OUT_ROOT)).absolute()


@dataclass(frozen=True)
class Layout:
    out_root: Path
    dataset: str

    def __post_init__(self):
        object.__setattr__(self, "out_root", Path(self.out_root).absolute())

    @property
    def root(self) -> Path:
        return self.out_root / self.dataset

    @property
    def dataset_json(self) -> Path:
        return self.root / "dataset.json"

    @property
    def raw(self) -> Path:
        return self.root / "raw"

    @property
    def manifest(self) -> Path:
        return self.raw / "manifest.json"

    @property
    def extracted(self) -> Path:
        return self.root / "extracted"

    @property
    def groundtruth(self) -> Path:
        return self.root / "groundtruth"

    @property
    def splits(self) -> Path:
        return self.root / "splits"

    @property
    def fits(self) -> Path:
        return self.root / "fits"

    @property
    def calibration(self) -> Path:
        return self.root / "calibration"

    @property
    def eval(self) -> Path:
        return self.root / "eval"

    @property
    def reports(self) -> Path:
        return self.root / "reports"

    @property
    def discovery(self) -> Path:
        return self.root / "discovery"

    @property
    def mlflow_uri(self) -> str:
        return "sqlite:///" + str(self.out_root / "mlflow.db")

    @property
    def mlflow_artifacts(self) -> Path:
        return self.out_root / "mlartifacts"

    def split_file(self, terrain: str, split: str, sequence: str) -> Path:
        return self.splits / terrain / split / f"{sequence}.parquet"

    def fit_file(self, model: str, terrain: str, inputs: str = "commanded") -> Path:
        """The fit of ``model`` on ``terrain`` under the input protocol ``inputs``
        (pipeline/core/protocol.py):
        ``<terrain>.json`` for ``commanded``, ``<terrain>.<inputs>.json`` for the others (a fit under one
        protocol is never another's)."""
        return (
            self.fits / model / (f"{terrain}.json" if inputs == "commanded" else f"{terrain}.{inputs}.json")
        )

    def eval_stem(self, model: str, terrain: str, inputs: str = "commanded") -> Path:
        """``eval/<model>/<terrain>[.<inputs>]``: the evaluate stage's per-run files add a suffix to it."""
        return self.eval / model / (terrain if inputs == "commanded" else f"{terrain}.{inputs}")

    def calibration_file(self, terrain: str) -> Path:
        return self.calibration / f"{terrain}.json"

    def split_files(
        self, manifest: Manifest, terrain: str | None = None, split: str | None = None
    ) -> list[Path]:
        """The split files of the manifest's train/cv/ld sequences (optionally one terrain and/or split),
        sorted, whether written yet or not (callers check)."""
        from skidbench.pipeline.core.manifest import SPLITS

        return sorted(
            self.split_file(s.terrain, s.category, s.name)
            for s in manifest.sequences
            if s.category in SPLITS and terrain in (None, s.terrain) and split in (None, s.category)
        )

    def require_split_files(
        self,
        manifest: Manifest,
        terrain: str | None = None,
        split: str | None = None,
        error: type[Exception] = ConfigError,
        prefix: str = "",
    ) -> list[Path]:
        """:meth:`split_files`, every one of them written: the one lookup of a stage's split files. A
        missing one raises ``error`` (the calling stage's error class) with one line naming it, how many
        more are missing and to run ``skidbench split``; ``prefix`` (e.g. ``"model edd: "``) goes first."""
        files = self.split_files(manifest, terrain, split)
        missing = [p for p in files if not p.is_file()]
        if missing:
            more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
            raise error(
                f"{prefix}{missing[0]}: no split file for sequence {missing[0].stem} of {self.manifest}"
                f"{more}; run `skidbench split`"
            )
        return files


def split_terrains(manifest: Manifest) -> list[str]:
    """The terrains with at least one train/cv/ld sequence in the manifest, sorted."""
    from skidbench.pipeline.core.manifest import SPLITS

    return sorted({s.terrain for s in manifest.sequences if s.category in SPLITS})


def remove_atomic(path: Path) -> None:
    """Remove a file, or a folder atomically (renamed aside in one step, then deleted). Gone already (a
    concurrent stage of a sweep pruned it first) is fine."""
    with contextlib.suppress(FileNotFoundError):
        if path.is_dir() and not path.is_symlink():
            aside = path.with_name(f".tmp-stale-{path.name}.{os.getpid()}")
            os.replace(path, aside)
            shutil.rmtree(aside, ignore_errors=True)
        else:
            path.unlink()


def _remove_empty_dirs(top: Path) -> None:
    """Remove the empty folders under ``top`` (deepest first); ``top`` itself is kept."""
    if not top.is_dir():
        return
    for d in sorted((p for p in top.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
        with contextlib.suppress(OSError):
            d.rmdir()  # only succeeds when empty


def prune_stale(layout: Layout, manifest: Manifest) -> list[Path]:
    """Remove the outputs of ``layout``'s dataset that belong to no sequence of ``manifest``: extracted
    folders, ground-truth files, split files (and the folders left empty), fits of terrains it lacks.
    Each removal is atomic (a file unlink or a folder rename); returns what was removed. Only this
    dataset's folder is touched."""
    names = {s.name for s in manifest.sequences}
    removed: list[Path] = []
    if layout.extracted.is_dir():
        for d in layout.extracted.iterdir():
            if d.is_dir() and (d.name not in names or d.name.startswith(".tmp-stale-")):
                removed.append(d)
    if layout.groundtruth.is_dir():
        for tum in layout.groundtruth.glob("*.tum"):
            if tum.stem not in names:
                removed += [tum, *[p for p in [tum.with_suffix(".json")] if p.is_file()]]
    keep = set(layout.split_files(manifest))
    if layout.splits.is_dir():
        removed += [
            p for p in layout.splits.glob("*/*/*.parquet") if p not in keep and not p.name.startswith(".")
        ]
    terrains = set(split_terrains(manifest))
    if layout.fits.is_dir():
        # fits/<model>/<terrain>[.<suffix>].json (and a learned model's <terrain>.arrays.npz); names
        # starting with "_" or "." are not per terrain
        removed += [
            p for p in [*layout.fits.glob("*/*.json"), *layout.fits.glob("*/*.npz")]
            if p.name.split(".")[0] not in terrains and not p.name.startswith(("_", "."))
        ]  # fmt: skip
    if layout.calibration.is_dir():
        removed += [p for p in layout.calibration.glob("*.json") if p.stem not in terrains]
    for p in removed:
        remove_atomic(p)
    _remove_empty_dirs(layout.splits)
    _remove_empty_dirs(layout.fits)
    return removed


def layout_from_cfg(cfg) -> Layout:
    """The layout of ``cfg``'s dataset (``out_root``, ``dataset``: :class:`CommonSettings`, read with
    :func:`root_from_cfg`, which registers the config's resolvers first: ``dataset`` resolves lazily, so a
    library caller that composed the config without the CLI gets its dataset name too)."""
    common = root_from_cfg(cfg, CommonSettings)
    return Layout(Path(common.out_root), common.dataset)


# -- dataset names (the folder under out_root a configured source writes to) ----------------------

NAME_FP_LEN = 6


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_.") or "root"


def fingerprint_of(key: dict[str, Any]) -> str:
    """sha256 of a JSON key, 12 hex digits."""
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]


def data_path(source: Any) -> Path:
    """The resolved absolute path of a source's data: ``source.root`` (+ ``source.file`` when set)."""
    if OmegaConf.is_config(source) and OmegaConf.is_missing(source, "root"):
        raise ConfigError(
            f"source.root is not set for source={source.get('name')}: give source.root=<folder>, or "
            "dataset=<name> of a dataset already under out_root (`skidbench datasets` lists them)"
        )
    path = Path(str(source.get("root"))).expanduser().resolve()
    file = source.get("file")
    if file and not isinstance(file, str) and hasattr(file, "__len__"):  # several files: one dataset
        return path / "+".join(Path(str(f)).stem for f in file)
    if file:
        path = path / str(file)
    return path


#: a file up to this size is hashed whole for the dataset's identity; a larger one by its size and three
#: blocks of ``CONTENT_BLOCK`` bytes (start, middle, end): a 4 GB bag costs 192 KiB of reading, not 4 GB
#: (recordings differ in their first bytes already: headers, time stamps). The stages' own stamps still
#: hash every file they read in full (pipeline/core/cache.py), so an edit the sample misses is still re-run.
CONTENT_FULL_MAX = 1 << 20
CONTENT_BLOCK = 64 << 10
_content_memo: dict[str, tuple[tuple[int, int, int], str]] = {}


def _content_hash(path: Path) -> str:
    """BLAKE2b-128 of a file's content (a large file: of its size and three blocks), memoised by
    (size, mtime, inode) for the life of the process."""
    st = path.stat()
    stat_key = (st.st_size, st.st_mtime_ns, st.st_ino)
    hit = _content_memo.get(str(path))
    if hit and hit[0] == stat_key:
        return hit[1]
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as fh:
        if st.st_size <= CONTENT_FULL_MAX:
            while block := fh.read(CONTENT_BLOCK):
                h.update(block)
        else:
            h.update(str(st.st_size).encode())
            for offset in (0, (st.st_size - CONTENT_BLOCK) // 2, st.st_size - CONTENT_BLOCK):
                fh.seek(offset)
                h.update(fh.read(CONTENT_BLOCK))
    _content_memo[str(path)] = (stat_key, h.hexdigest())
    return h.hexdigest()


def data_files(source: Any, exclude: Path | None = None) -> list[tuple[str, Path]]:
    """The files that are a source's data, as (path relative to ``source.root``, path), sorted: the files
    ``source.file`` names, else every file under ``source.root`` (hidden names and the output root
    ``exclude``, when it lies inside, left out)."""
    data_path(source)  # the one-line error of a missing root
    root = Path(str(source.get("root"))).expanduser().resolve()
    file = source.get("file")
    if file:
        names = (
            [str(file)] if isinstance(file, str) or not hasattr(file, "__len__") else [str(f) for f in file]
        )
        return sorted((Path(n).as_posix(), (root / n).resolve()) for n in names)
    if root.is_file():
        return [(root.name, root)]
    skip = Path(exclude).expanduser().resolve() if exclude is not None else None
    out = []
    for dirpath, dirnames, filenames in os.walk(root):
        here = Path(dirpath)
        dirnames[:] = sorted(d for d in dirnames if not d.startswith(".") and (here / d).resolve() != skip)
        out += [
            ((here / f).relative_to(root).as_posix(), here / f) for f in filenames if not f.startswith(".")
        ]
    return sorted(out)


def data_key(source: Any, exclude: Path | None = None) -> dict[str, Any]:
    """The identity key of a source's data: the source kind and its content, i.e. each file's path
    relative to the root, size and content hash (:func:`data_files`), never where it is mounted: the same
    files under two mount points, or on two machines, are one dataset. A missing file counts as such (the
    reader says so in its own words)."""
    files = []
    for rel, path in data_files(source, exclude):
        try:
            files.append([rel, path.stat().st_size, _content_hash(path)])
        except OSError:
            files.append([rel, None, None])
    return {"source": str(source.get("name")), "content": files}


def path_key(source: Any) -> dict[str, str]:
    """The key a dataset's folder name is made from: the source kind and the data's resolved path. The
    folder is the data's home on this machine (it survives edits of the files: the stages' stamps re-run
    what depends on a changed file); the identity is :func:`data_key`."""
    return {"source": str(source.get("name")), "root": str(data_path(source))}


def auto_name(prefix: str, source: Any) -> str:
    """``<prefix>-<root name>-<fingerprint[:6]>`` (``<prefix>-<label>`` when ``source.label`` is set), the
    fingerprint of :func:`path_key`."""
    if source.get("label"):
        return f"{prefix}-{_safe(str(source.get('label')))}"
    path = data_path(source)
    stem = path.stem if path.is_file() else path.name
    return f"{prefix}-{_safe(stem)}-{fingerprint_of(path_key(source))[:NAME_FP_LEN]}"


def sim_name(scale: str, seed: Any) -> str:
    """``sim-<scale>`` (``-seed<n>`` for a seed other than 0)."""
    seed = int(seed or 0)
    return f"sim-{scale}" + (f"-seed{seed}" if seed else "")


def _dataset_name(prefix, _root_):
    return auto_name(str(prefix), _root_.source)


def _sim_dataset_name(scale, seed):
    return sim_name(str(scale), seed)


def register_resolvers() -> None:
    """Registers the config's dataset names (conf/source/*.yaml) with OmegaConf:
    ``${skidbench.dataset:<prefix>}`` and ``${skidbench.sim_dataset:<scale>,<seed>}``. Idempotent. The
    entry points call it before a config is composed or resolved, as Hydra's docs do before
    ``@hydra.main``: the CLI (``pipeline/cli/main.py``: ``main``, each stage app's ``stage`` decorator and its
    task function, so a sweep's job in another process has them), the override check's and ``inspect``'s
    compose, and :func:`layout_from_cfg` (library callers); importing this module registers nothing."""
    if not OmegaConf.has_resolver("skidbench.dataset"):
        OmegaConf.register_new_resolver("skidbench.dataset", _dataset_name)
    if not OmegaConf.has_resolver("skidbench.sim_dataset"):
        OmegaConf.register_new_resolver("skidbench.sim_dataset", _sim_dataset_name)
