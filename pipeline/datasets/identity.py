"""A dataset's identity: which data an output folder ``<out_root>/<dataset>`` holds.

Name (the output folder and the MLflow experiment ``skidbench-<name>``):
- ``source.dataset`` when the user sets it (or, for ``drive_df``, ``source.label``: ``drive-<label>``);
- the simulated source: ``sim-<scale>``, ``sim-<scale>-seed<N>`` for a seed other than 0 (scale and seed
  are its identity: the same pair gives the same bytes);
- any other source: ``<prefix>-<root name>-<path fingerprint[:6]>``, e.g. ``amrl-grass_day2-3f9c1a``, the
  fingerprint of the source kind and the resolved path of its data (``layout.path_key``): the data's home
  on this machine, which survives edits of its files (the stages' stamps re-run exactly what depends on a
  changed file, pruning removes the outputs of sequences that are gone).

The dataset's identity, its fingerprint (the run tag ``skidbench.dataset_id``), is the data's content, not
where it is mounted (``layout.data_key``): the source kind and each file's path relative to
``source.root`` (or the files ``source.file`` names), size and content hash (a file over 1 MiB: its size
and three 64 KiB blocks). Measured 2026-11-25 on a loaded 2-core machine: the 23 files (498 MB) of
`mini`'s bags 0.06-0.08 s, the 13 files (19 MB) of ../shared/data/real 0.05 s, once per process (then
memoised by size, time and inode). Two mount points or two machines holding the same files are one
dataset id (their runs are compared as one dataset's); the simulated source's is its scale and seed (the
same pair gives the same bytes). Files hidden by name (``.*``) and the output root, when it lies inside the
data's root, are not part of it.

Each stage records the identity in ``<ds>/dataset.json`` (schema 2: name, source, root, fingerprint,
terrains, sequences; written atomically). A folder whose recorded root holds other content now (its files
were edited, or the record was made by a release whose fingerprint was the root's path: schema 1) is
updated with a note that its identity moved: runs logged under the old id are not ranked with new ones.
A folder recorded for another root is taken over when that root holds the same content (the data moved to
another mount point) and refused otherwise, in one line naming both roots, unless ``source.replace=true``
(the old folder is then removed; its MLflow runs stay, but carry the old fingerprint in
``skidbench.dataset_id``, so compare never mixes them in).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import logging
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from skidbench.pipeline.core.errors import ConfigError
from skidbench.pipeline.core.io import write_json_atomic
from skidbench.pipeline.core.layout import (
    CommonSettings,
    Layout,
    data_key,
    data_path,
    fingerprint_of,
    prune_stale,
    remove_atomic,
    root_from_cfg,
)
from skidbench.pipeline.core.manifest import Manifest
from skidbench.pipeline.sources import registry
from skidbench.pipeline.sources.contract import Source, settings_from

log = logging.getLogger("skidbench.dataset")

RECORD_SCHEMA = 2  # 2: the fingerprint is the data's content (1: the root's path)


class DatasetError(ConfigError):
    """Two datasets that would share one output folder."""


@dataclass(frozen=True)
class DatasetIdentity:
    name: str
    source: str  # source.name: sim | bag | amrl_txt | drive_df | ...
    root: str  # the resolved data path (sim: the raw folder it simulates into)
    fingerprint: str  # sha256 of the identity key, 12 hex digits

    def describe(self) -> str:
        return f"dataset {self.name} ({self.source} {self.root}, fingerprint {self.fingerprint})"


def is_sim(source: Any) -> bool:
    return str(source.get("name")) == "sim"


def read_record(layout: Layout) -> dict[str, Any] | None:
    try:
        return json.loads(layout.dataset_json.read_text())
    except (OSError, ValueError):
        return None


def identity_from_cfg(cfg: Any, common: CommonSettings | None = None) -> DatasetIdentity:
    """The identity of the configured dataset. A source whose ``root`` is not given (``dataset=<name>``
    alone, e.g. for ``compare``) takes the identity recorded in that dataset's folder. ``common``: the
    config's common keys when the caller has read them (:func:`root_from_cfg`)."""
    common = common or root_from_cfg(cfg, CommonSettings)
    layout = Layout(Path(common.out_root), common.dataset)
    source = cfg.source
    if is_sim(source):
        key = {"source": "sim", "scale": str(cfg.scale.name), "seed": int(common.seed or 0)}
        return DatasetIdentity(layout.dataset, "sim", str(layout.raw), fingerprint_of(key))
    if OmegaConf.is_config(source) and OmegaConf.is_missing(source, "root"):
        rec = read_record(layout)
        if rec and rec.get("fingerprint"):
            return DatasetIdentity(
                layout.dataset, str(rec["source"]), str(rec["root"]), str(rec["fingerprint"])
            )
        data_path(source)  # the one-line error
    key = data_key(source, Path(common.out_root))
    return DatasetIdentity(layout.dataset, key["source"], str(data_path(source)), fingerprint_of(key))


def _unwrap(exc: BaseException) -> BaseException:
    """The ConfigError behind an OmegaConf interpolation error (a resolver's one-line message)."""
    seen = exc
    while seen is not None and not isinstance(seen, ConfigError):
        seen = seen.__cause__ or seen.__context__
    return seen or exc


@dataclass(frozen=True)
class Home:
    """What opening a dataset's folder needs of the config (:func:`home_from_cfg`): the output root, the
    configured identity and whether a folder holding another source may be replaced."""

    out_root: Path
    ident: DatasetIdentity
    replace: bool = False


def home_from_cfg(cfg: Any) -> Home:
    """The :class:`Home` of a composed config. A source's settings that contradict each other (the
    source's ``check``, e.g. more terrains than files) are refused first, by every stage, not only by the
    one that reads them; an interpolation's one-line error (a missing root) is raised as itself."""
    from omegaconf.errors import OmegaConfBaseException

    try:
        source = OmegaConf.to_container(cfg.source, resolve=True, throw_on_missing=False)
        check_source_settings(source)
        common = root_from_cfg(cfg, CommonSettings)
        ident = identity_from_cfg(cfg, common)
    except OmegaConfBaseException as exc:
        cause = _unwrap(exc)
        if isinstance(cause, ConfigError):
            raise cause from None
        raise
    return Home(Path(common.out_root), ident, bool(source.get("replace", False)))


def open_home(home: Home, stage: str = "") -> tuple[Layout, DatasetIdentity]:
    """At the start of a stage: the dataset's identity, printed; its folder checked against the recorded
    identity (DatasetError naming both roots unless ``source.replace=true``); ``dataset.json`` written;
    outputs of sequences that are no longer in the manifest pruned."""
    ident = home.ident
    layout = Layout(home.out_root, ident.name)
    # stdout: stderr is kept for the one-line error a stage may end with
    print(f"skidbench {stage}: {ident.describe()} -> {layout.root}", flush=True)
    rec = read_record(layout)
    if rec is not None and rec.get("fingerprint") != ident.fingerprint:
        if rec.get("source") == ident.source and rec.get("root") == ident.root:
            # the same root, other content: its files were edited (the folder stays their home: the
            # stamps re-run what depends on the changed files), or the folder was recorded by a release
            # whose identity was the root's path (schema 1)
            why = "recorded by its path by an earlier release" if int(rec.get("schema", 1)) < 2 else "edited"
            print(
                f"skidbench {stage}: note: {ident.root} changed since {layout.root} recorded it ({why}): its "
                f"identity is now fingerprint {ident.fingerprint} (was {rec.get('fingerprint')}); MLflow "
                "runs logged under the old one are not ranked with new ones: run evaluate again",
                flush=True,
            )
        elif not home.replace:
            raise DatasetError(
                f"{layout.root}: dataset {ident.name!r} already holds {rec.get('source')} {rec.get('root')}; "
                f"{ident.source} {ident.root} cannot share it: name it with source.dataset=<another name>, "
                "or set source.replace=true to replace it"
            )
        else:
            log.warning(
                "source.replace=true: removing %s (%s %s)", layout.root, rec.get("source"), rec.get("root")
            )
            remove_atomic(layout.root)
    record(layout, ident)
    if layout.manifest.is_file():
        prune_stale(layout, Manifest.read(layout.manifest))
    return layout, ident


def check_source_settings(source: Mapping[str, Any]) -> None:
    """The installed source's ``check`` of its settings (``source``: the config section as a plain
    mapping). A kind no installed source has is left to the stage that reads the source (extract names
    the installed ones): an imported dataset (``source=bundle``) has none, and a stage after extract
    reads only the extracted tables; so is a setting not given at all (``dataset=<name>`` alone names a
    dataset without its root)."""
    kind = str(source.get("kind") or "bag")
    if kind not in registry.installed():
        return
    cls = registry.source_class(kind)
    if cls.check is Source.check:  # the source checks nothing
        return
    try:
        settings = settings_from(cls.Settings, source, kind)
    except ConfigError:
        return
    cls().check(settings)


def record(layout: Layout, ident: DatasetIdentity) -> dict[str, Any]:
    """Write ``<ds>/dataset.json`` (only when its content changes): the identity and the manifest's
    terrains and sequence count."""
    doc: dict[str, Any] = {"schema": RECORD_SCHEMA, **asdict(ident), "terrains": [], "sequences": 0}
    if layout.manifest.is_file():
        with contextlib.suppress(ConfigError):
            m = Manifest.read(layout.manifest)
            doc.update(terrains=m.terrains, sequences=len(m.sequences))
    if read_record(layout) != doc:
        write_json_atomic(layout.dataset_json, doc)
    return doc


def holds_data(root: Path) -> bool:
    """True when a dataset folder holds any file besides its identity (``dataset.json``), the manifest
    ``extract`` derives from a user's source before reading it, stamps and temporary files: a folder
    without data is what a command that failed first leaves."""
    for path in Path(root).rglob("*"):
        if not path.is_file():
            continue
        rel = path.relative_to(root)
        if rel in (Path("dataset.json"), Path("raw/manifest.json")) or rel.parts[0] == ".stamps":
            continue
        if path.name.startswith(".tmp-"):
            continue
        return True
    return False


def has_extracted_table(layout: Layout) -> bool:
    """At least one extracted table (``extracted/<seq>/<key>.parquet``): the least a dataset holds."""
    return layout.extracted.is_dir() and any(layout.extracted.glob("*/*.parquet"))


# -- `skidbench datasets` --------------------------------------------------------------------------
def list_datasets(out_root: Path) -> list[dict[str, Any]]:
    """One row per dataset folder under ``out_root`` (a folder with ``dataset.json`` or a manifest, and at
    least one extracted table):
    name, source, root, terrains, fingerprint, last evaluate (UTC time and parent run id)."""
    rows = []
    root = Path(out_root)
    if not root.is_dir():
        return rows
    for d in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        layout = Layout(root, d.name)
        rec = read_record(layout)
        imported = (rec or {}).get("source") == "bundle"  # `skidbench import`: splits, no extracted tables
        if (rec is None and not layout.manifest.is_file()) or not (has_extracted_table(layout) or imported):
            continue  # not a dataset yet (what a failed first command or a bare simulate leaves)
        rec = rec or {"source": "?", "root": "?", "fingerprint": "?"}
        terrains = rec.get("terrains") or []
        if not terrains and layout.manifest.is_file():
            with contextlib.suppress(ConfigError):
                terrains = Manifest.read(layout.manifest).terrains
        last = "-"
        ev = layout.eval / "last_evaluate.json"
        with contextlib.suppress(OSError, ValueError):
            run = json.loads(ev.read_text()).get("parent_run_id", "?")
            when = dt.datetime.fromtimestamp(ev.stat().st_mtime, dt.UTC).strftime("%Y-%m-%d %H:%M")
            last = f"{when} UTC (run {run})"
        rows.append(
            {
                "name": d.name,
                "source": rec.get("source", "?"),
                "root": rec.get("root", "?"),
                "terrains": ",".join(terrains) or "-",
                "fingerprint": rec.get("fingerprint", "?"),
                "last_evaluate": last,
            }
        )
    return rows


def format_datasets(rows: list[dict[str, Any]], out_root: Path) -> str:
    if not rows:
        return f"{out_root}: no datasets"
    cols = ["name", "source", "root", "terrains", "last_evaluate"]
    head = {c: c.replace("_", " ") for c in cols}
    width = {c: max(len(head[c]), *(len(str(r[c])) for r in rows)) for c in cols}
    lines = ["  ".join(head[c].ljust(width[c]) for c in cols).rstrip()]
    lines += ["  ".join(str(r[c]).ljust(width[c]) for c in cols).rstrip() for r in rows]
    return "\n".join(lines)
