"""A released benchmark: ``skidbench export <dataset> <dir>`` writes a dataset and its board as a bundle
(a folder of plain files), ``skidbench import <dir>`` verifies one and makes a dataset of it.

A bundle (format ``skidbench-bundle`` version :data:`BUNDLE_VERSION`)::

    bundle.json                    what it is: the dataset (name, source, identity), the robot (name and
                                   constants), every sequence (terrain, split, file, rows, seconds), the
                                   protocol and metric versions and the settings the board was scored with,
                                   the calibration settings, the licence and provenance of the source data,
                                   the skidbench version and commit that wrote it
    SHA256SUMS                     the sha256 of every other file (``sha256sum -c SHA256SUMS`` checks it)
    README.md                      what is in it and how to use it (import, score, the inputs contract)
    card.md                        the dataset card (the paper's Table I for these splits)
    splits/<terrain>/<train|cv|ld>/<seq>.parquet     the split files, byte for byte (pipeline/core/schema.py)
    calibration/<terrain>.json     the effective wheel radius and track width and the wheel response
    board/<protocol>.csv|json      the board of each protocol evaluated, every row with its provenance
                                   (benchmark/board/boards.py)
    inputs/<protocol>/<terrain>/<split>/<seq>.parquet   the exact table a model is run on under the chosen
                                   protocol (``inputs=``): pipeline/core/protocol.py ``model_inputs``, the
                                   columns ``INPUT_COLUMNS`` only, never the targets, the pose or the
                                   encoders

Import checks every file against ``SHA256SUMS`` before anything is written (a missing, changed or unlisted
file is one line naming it) and builds ``<out_root>/<name>/`` (pipeline/datasets/imported.py) in a temporary
folder
renamed into place: nothing is half-written. Evaluate on it (``source=bundle dataset=<name>``) refits the
same built-in models on the same bytes and scores them the same way, so its board equals the exported one
cell for cell.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import importlib.metadata as md
import json
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa

from skidbench.benchmark.board import boards as brd
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.tracking import store as trk
from skidbench.pipeline.core.errors import SkidbenchError, one_line
from skidbench.pipeline.core.io import sha256_file, write_json_atomic, write_parquet_atomic, write_text_atomic
from skidbench.pipeline.core.layout import Layout, fingerprint_of, remove_atomic, split_terrains
from skidbench.pipeline.core.manifest import SPLITS, Manifest
from skidbench.pipeline.core.manifest import Sequence as ManifestSequence
from skidbench.pipeline.core.protocol import INPUT_COLUMNS, PROTOCOL_VERSION, model_inputs
from skidbench.pipeline.core.schema import read_split
from skidbench.pipeline.datasets.identity import DatasetIdentity, read_record, record
from skidbench.pipeline.datasets.imported import RECORD_DIR, SOURCE
from skidbench.pipeline.runner import environment

BUNDLE_FORMAT = "skidbench-bundle"
BUNDLE_VERSION = 1
SUMS = "SHA256SUMS"
#: the metric every board of a bundle is scored with (benchmark/scoring/horizon.py), and its version
METRIC = {
    "name": "rmsre",
    "version": 1,
    "definition": "root mean square over every window of the horizon of the relative translational error "
    "(position error / distance travelled) and the relative rotational error (|yaw error| / absolute "
    "rotation), in %; windows under min_distance_m / min_rotation_deg are left out of that error",
}
#: the licence of data skidbench simulated (the project's own licence; no third party's data)
SIMULATED_LICENCE = "BSD-3-Clause (simulated by skidbench; no third-party data)"


class BundleError(SkidbenchError):
    """A bundle that cannot be written or read (missing pieces, a failed checksum, a folder in the way)."""


# -- checksums ---------------------------------------------------------------------------------------
def bundle_files(folder: Path) -> list[str]:
    """Every file of a bundle folder but ``SHA256SUMS``, as sorted POSIX paths relative to it."""
    return sorted(
        p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file() and p.name != SUMS
    )


def write_sums(folder: Path) -> Path:
    """``<folder>/SHA256SUMS`` in ``sha256sum``'s format (``<hex>  <path>``), one line per file."""
    lines = [f"{sha256_file(folder / rel)}  {rel}" for rel in bundle_files(folder)]
    write_text_atomic(folder / SUMS, "\n".join(lines) + "\n")
    return folder / SUMS


def read_sums(folder: Path) -> dict[str, str]:
    """``{path: sha256}`` of a bundle's ``SHA256SUMS``; BundleError when it is missing or malformed."""
    path = folder / SUMS
    if not path.is_file():
        raise BundleError(f"{path}: missing; not a skidbench bundle, or an incomplete copy of one")
    out = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        m = re.fullmatch(r"([0-9a-f]{64}) [ *](.+)", line.strip())
        if not m:
            raise BundleError(f"{path}: line {n} is not '<sha256>  <file>': {line[:80]!r}")
        out[m.group(2)] = m.group(1)
    return out


def verify(folder: Path) -> dict[str, str]:
    """Checks every file of a bundle against ``SHA256SUMS``: BundleError (one line naming the file) for a
    listed file that is missing or whose sha256 differs, and for a file the list does not hold. Returns
    the list."""
    folder = Path(folder)
    if not folder.is_dir():
        raise BundleError(f"{folder}: no such folder")
    sums = read_sums(folder)
    if "bundle.json" not in sums:
        raise BundleError(f"{folder / SUMS}: does not list bundle.json; not a skidbench bundle")
    for rel, want in sums.items():
        path = folder / rel
        if not path.is_file():
            raise BundleError(f"{path}: listed in {SUMS} but missing; the bundle is incomplete")
        got = sha256_file(path)
        if got != want:
            raise BundleError(
                f"{path}: sha256 {got[:16]}... differs from {SUMS}'s {want[:16]}...; the file is corrupted "
                "or was changed since export"
            )
    extra = [rel for rel in bundle_files(folder) if rel not in sums]
    if extra:
        raise BundleError(
            f"{folder / extra[0]}: not listed in {SUMS}; a bundle holds only the files it lists"
        )
    return sums


def content_id(folder: Path) -> str:
    """The identity of a bundle's content: the fingerprint of its ``SHA256SUMS`` (12 hex digits)."""
    return fingerprint_of({"source": SOURCE, "sha256": sha256_file(Path(folder) / SUMS)})


# -- export ------------------------------------------------------------------------------------------
@dataclass
class ExportResult:
    folder: Path
    files: int
    bytes: int
    boards: list[str]
    inputs: str
    sequences: int


def _version() -> str:
    try:
        return md.version("skidbench")
    except md.PackageNotFoundError:  # pragma: no cover
        return "unknown"


def _calibration_settings(layout: Layout, terrain: str) -> dict[str, Any] | None:
    """The settings the terrain's calibration was made with (its stamp's), or None."""
    from skidbench.pipeline.calibrate.calibration import calibration_stamp

    conf = calibration_stamp(layout, terrain).data.get("config") or {}
    return conf.get("settings") if isinstance(conf, dict) else None


@dataclass(frozen=True)
class ExportSettings:
    """What ``export`` reads of its config: the robot (``robot``) and calibrations the inputs are made
    with, the input protocol written (``inputs``), the source data's ``bundle.licence`` and
    ``bundle.provenance`` (None: unset)."""

    robot: Any  # pipeline.robot.Robot
    calibrations: Any  # pipeline.calibration.Calibrations
    inputs: str
    licence: str | None
    provenance: str | None

    @classmethod
    def from_cfg(cls, cfg: Any) -> ExportSettings:
        from skidbench.pipeline.calibrate.calibration import Calibrations
        from skidbench.pipeline.core.robot import robot_from_hydra

        b = cfg.bundle
        return cls(
            robot_from_hydra(cfg.robot), Calibrations.from_cfg(cfg), str(cfg.get("inputs") or "commanded"),
            str(b.get("licence")) if b.get("licence") else None, b.get("provenance") or None,
        )  # fmt: skip


def licence_of(licence: str | None, source: str) -> str:
    """The licence of the source data: ``bundle.licence``; for simulated data the project's own."""
    lic = licence
    if lic:
        return str(lic)
    if source == "sim":
        return SIMULATED_LICENCE
    raise BundleError(
        f"bundle.licence is not set: a bundle states the licence of its source data ({source}); set "
        "bundle.licence='<SPDX id or the terms, e.g. CC-BY-4.0>' "
        "(and bundle.provenance='<where it comes from>')"
    )


def _sequences(layout: Layout, manifest: Manifest) -> list[dict[str, Any]]:
    out = []
    for seq in manifest.sequences:
        if seq.category not in SPLITS:
            continue
        path = layout.split_file(seq.terrain, seq.category, seq.name)
        df, meta = read_split(path)
        t = df["t"].to_numpy(float)
        out.append(
            {
                "name": seq.name,
                "terrain": seq.terrain,
                "split": seq.category,
                "file": path.relative_to(layout.root).as_posix(),
                "rows": int(len(df)),
                "duration_s": float(t[-1] - t[0]) if len(t) > 1 else 0.0,
                "rate_hz": meta.get("rate_hz"),
                "sources": meta.get("sources"),
            }
        )
    return out


def _write_inputs(s: ExportSettings, layout: Layout, manifest: Manifest, dest: Path) -> int:
    """``inputs/<protocol>/<terrain>/<split>/<seq>.parquet``: :func:`model_inputs` of every split file
    (Train too: a model fitted under the protocol is fitted on its inputs and the Train targets)."""
    from skidbench.pipeline.calibrate.calibration import response_for

    robot, protocol = s.robot, s.inputs
    n = 0
    for terrain in split_terrains(manifest):
        response = response_for(s.calibrations, terrain) if protocol == "response" else None
        if protocol == "response" and response is None:
            raise BundleError(
                f"inputs=response: {layout.calibration_file(terrain)}: no wheel response identified for "
                f"terrain {terrain}; export inputs=commanded (or measured)"
            )
        for path in layout.require_split_files(manifest, terrain, None, BundleError):
            df, meta = read_split(path)
            seq = str(meta.get("sequence") or path.stem)
            table = model_inputs(df.assign(sequence=seq), protocol, robot, response)
            out = dest / "inputs" / protocol / path.relative_to(layout.splits)
            write_parquet_atomic(
                pa.Table.from_pandas(table[list(INPUT_COLUMNS)], preserve_index=False),
                out,
                {
                    "sequence": seq,
                    "terrain": terrain,
                    "split": path.parent.name,
                    "inputs": protocol,
                    "protocol_version": PROTOCOL_VERSION,
                    "robot": robot.name,
                },  # fmt: skip
            )
            n += 1
    return n


def export_bundle(s: ExportSettings, layout: Layout, dest: Path, tracker: trk.Tracker | None) -> ExportResult:
    """Writes the bundle of ``layout``'s dataset to ``dest`` (a new or empty folder), atomically: built in
    a temporary sibling folder, renamed into place when complete."""
    dest = Path(dest).expanduser().absolute()
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise BundleError(f"{dest}: exists and is not an empty folder; export to a new folder")
    if not layout.manifest.is_file():
        raise BundleError(
            f"{layout.root}: no dataset here (no {layout.manifest}); `skidbench datasets` lists them"
        )
    rec = read_record(layout) or {}
    lic = licence_of(s.licence, str(rec.get("source", "?")))
    manifest = Manifest.read(layout.manifest)
    terrains = split_terrains(manifest)
    if not terrains:
        raise BundleError(f"{layout.manifest}: no train/cv/ld sequences; nothing to export")
    files = layout.require_split_files(manifest, None, None, BundleError)
    for t in terrains:
        if not layout.calibration_file(t).is_file():
            raise BundleError(
                f"{layout.calibration_file(t)}: missing; run `skidbench calibrate` (a bundle ships the "
                "calibration every fit is built with)"
            )
    boards = brd.all_boards(tracker) if tracker is not None else {}
    if not boards:
        raise BundleError(
            f"{layout.root}: no `skidbench evaluate` run of dataset {layout.dataset} in the MLflow store; "
            "run it first (a bundle ships the board)"
        )
    protocol = s.inputs

    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".tmp-export-{dest.name}.{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        for p in files:
            out = tmp / p.relative_to(layout.root)
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(p, out)
        card = layout.splits / "card.md"
        if card.is_file():
            shutil.copyfile(card, tmp / "card.md")
        calib_settings = {}
        for t in terrains:
            (tmp / "calibration").mkdir(exist_ok=True)
            shutil.copyfile(layout.calibration_file(t), tmp / "calibration" / f"{t}.json")
            calib_settings[t] = _calibration_settings(layout, t)
        for b in boards.values():
            brd.write_board(
                b, tmp / "board", {"dataset": layout.dataset, "dataset_id": rec.get("fingerprint")}
            )
        n_inputs = _write_inputs(s, layout, manifest, tmp)
        doc = _bundle_doc(s, layout, rec, manifest, boards, lic, calib_settings)
        write_json_atomic(tmp / "bundle.json", doc)
        write_text_atomic(tmp / "README.md", _readme(doc))
        write_sums(tmp)
        if dest.exists():
            dest.rmdir()  # empty (checked above)
        os.replace(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    n_files = len(bundle_files(dest)) + 1
    size = sum(p.stat().st_size for p in dest.rglob("*") if p.is_file())
    return ExportResult(dest, n_files, size, list(boards), protocol, n_inputs)


def _bundle_doc(s: ExportSettings, layout, rec, manifest, boards, lic, calib_settings) -> dict[str, Any]:
    robot, protocol = s.robot, s.inputs
    first = next(iter(boards.values()))
    return {
        "format": BUNDLE_FORMAT,
        "version": BUNDLE_VERSION,
        "dataset": {
            "name": layout.dataset,
            "source": rec.get("source"),
            "root": rec.get("root"),
            "fingerprint": rec.get("fingerprint"),
            "terrains": split_terrains(manifest),
            "robot": manifest.robot,
        },
        "robot": {"name": robot.name, "spec": json.loads(json.dumps(robot.to_dict(), default=str))},
        "sequences": _sequences(layout, manifest),
        "protocol": {
            "version": PROTOCOL_VERSION,
            "input_columns": list(INPUT_COLUMNS),
            "inputs_written": protocol,
            "boards": list(boards),
        },
        "metric": {
            **METRIC,
            **{
                k: first.settings.get(k) for k in ("horizons", "splits", "min_distance_m", "min_rotation_deg")
            },
            # every metric the boards hold (benchmark/scoring/metrics.py): its MLflow name, unit and
            # definition
            "metrics": [
                {
                    "name": m.name,
                    "key": m.pattern(),
                    "unit": m.unit,
                    "definition": m.description,
                    "optional": m.optional,
                }
                for m in mt.METRICS
            ],
        },  # fmt: skip
        "calibration_settings": calib_settings,
        "licence": lic,
        "provenance": {
            "statement": s.provenance
            or (
                f"simulated by skidbench {_version()} (`skidbench simulate`), dataset {layout.dataset}"
                if rec.get("source") == "sim"
                else f"{rec.get('source')} data from {rec.get('root')}"
            ),
            "source": rec.get("source"),
            "root": rec.get("root"),
            "fingerprint": rec.get("fingerprint"),
            "imported_from": (read_bundle_doc(layout.root / RECORD_DIR) or {}).get("dataset"),
        },  # fmt: skip
        "written_by": {
            "skidbench": _version(),
            "git_commit": environment.git_commit(),
            "utc": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M:%S"),
        },
    }


def _readme(doc: dict[str, Any]) -> str:
    ds = doc["dataset"]
    seqs = doc["sequences"]
    boards = doc["protocol"]["boards"]
    proto = doc["protocol"]["inputs_written"]
    return "\n".join([
        f"# skidbench bundle: {ds['name']}",
        "",
        f"Robot `{doc['robot']['name']}`, terrains {', '.join(ds['terrains'])}; {len(seqs)} sequences "
        f"({sum(s['rows'] for s in seqs)} rows). Licence of the data: {doc['licence']}.",
        f"Provenance: {doc['provenance']['statement']}.",
        "",
        "Check it: `sha256sum -c SHA256SUMS`. Use it: `skidbench import <this folder>`, then "
        f"`{next_commands(doc, ds['name'])[0]}` re-scores the built-in models (the boards of "
        f"{', '.join(boards)} in `board/` are what they scored at export).",
        "",
        f"A model from anywhere: run it on `inputs/{proto}/<terrain>/<cv|ld>/<seq>.parquet` (columns "
        f"{', '.join(doc['protocol']['input_columns'])}; fit on `splits/<terrain>/train/`, which has the "
        "targets), write one Parquet or CSV with columns `sequence, t, vx, vy, wz` (body velocities, m/s "
        "and rad/s, one row per input row), then "
        f"`skidbench score {ds['name']} --predictions <file> inputs={proto}`.",
        "",
        f"Metric: {doc['metric']['definition']} (version {doc['metric']['version']}; horizons "
        f"{doc['metric'].get('horizons')} s, min distance {doc['metric'].get('min_distance_m')} m, min "
        f"rotation {doc['metric'].get('min_rotation_deg')} deg).",
        "",
    ])  # fmt: skip


def read_bundle_doc(folder: Path) -> dict[str, Any] | None:
    """``<folder>/bundle.json`` (a bundle, or an imported dataset's ``bundle/`` record), else None."""
    with contextlib.suppress(OSError, ValueError):
        doc = json.loads((Path(folder) / "bundle.json").read_text())
        return doc if isinstance(doc, dict) and doc.get("format") == BUNDLE_FORMAT else None
    return None


# -- import ------------------------------------------------------------------------------------------
@dataclass
class ImportResult:
    layout: Layout
    doc: dict[str, Any]
    imported: bool  # False: the same bundle was already imported there
    commands: list[str] = field(default_factory=list)


def _read_doc(folder: Path) -> dict[str, Any]:
    path = folder / "bundle.json"
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise BundleError(f"{path}: missing; {folder} is not a skidbench bundle") from None
    except (OSError, ValueError) as exc:
        raise BundleError(f"{path}: not readable JSON ({one_line(str(exc))})") from None
    if not isinstance(doc, dict) or doc.get("format") != BUNDLE_FORMAT:
        raise BundleError(
            f"{path}: not a skidbench bundle (format {doc.get('format') if isinstance(doc, dict) else '?'!r})"
        )
    if int(doc.get("version", 0)) > BUNDLE_VERSION:
        raise BundleError(
            f"{path}: bundle version {doc.get('version')} is newer than this skidbench reads "
            f"({BUNDLE_VERSION}); upgrade skidbench"
        )
    return doc


def _safe_rel(folder: Path, rel: str) -> Path:
    """``folder / rel`` for a relative path that stays inside ``folder`` (BundleError otherwise)."""
    path = (folder / rel).resolve()
    if not str(path).startswith(str(folder.resolve()) + os.sep):
        raise BundleError(f"{folder / 'bundle.json'}: file {rel!r} points outside the bundle")
    return path


def import_bundle(
    folder: Path, out_root: Path, name: str | None = None, replace: bool = False
) -> ImportResult:
    """Verifies the bundle at ``folder`` (every checksum) and makes the dataset ``<out_root>/<name>``
    (default name: the exported dataset's). Importing the same bundle again changes nothing; a folder
    holding another dataset is refused unless ``replace``."""
    folder = Path(folder).expanduser().resolve()
    sums = verify(folder)
    doc = _read_doc(folder)
    name = str(name or doc["dataset"]["name"])
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", name):
        raise BundleError(f"dataset name {name!r}: use letters, digits, '_', '.', '-' (set bundle.name=...)")
    ident = DatasetIdentity(name, SOURCE, str(folder), content_id(folder))
    layout = Layout(Path(out_root), name)
    commands = next_commands(doc, name)
    have = read_record(layout)
    if have is not None and have.get("fingerprint") == ident.fingerprint:
        _stamp_calibrations(layout, doc)  # what an interrupted import may not have finished
        return ImportResult(layout, doc, False, commands)
    if layout.root.exists() and any(layout.root.iterdir()):
        if not replace:
            what = f"{have.get('source')} {have.get('root')}" if have else "other files"
            raise BundleError(
                f"{layout.root}: dataset {name!r} already holds {what}; import under another name "
                "(bundle.name=<name>) or set source.replace=true to replace it"
            )
    tmp = Layout(layout.out_root, f".tmp-import-{name}.{os.getpid()}")
    shutil.rmtree(tmp.root, ignore_errors=True)
    tmp.root.mkdir(parents=True)
    try:
        seqs = []
        for s in doc["sequences"]:
            if s["file"] not in sums:
                raise BundleError(
                    f"{folder / 'bundle.json'}: sequence {s['name']}'s file {s['file']} is not in {SUMS}"
                )
            src = _safe_rel(folder, s["file"])
            out = tmp.split_file(s["terrain"], s["split"], s["name"])
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, out)
            final = layout.split_file(s["terrain"], s["split"], s["name"])
            rel = os.path.relpath(final, layout.raw)  # the manifest's paths are relative to its folder
            seqs.append(ManifestSequence(s["name"], s["terrain"], s["split"], rel))
        if (folder / "card.md").is_file():
            shutil.copyfile(folder / "card.md", tmp.splits / "card.md")
        for t in doc["dataset"]["terrains"]:
            src = folder / "calibration" / f"{t}.json"
            if src.is_file():
                tmp.calibration.mkdir(exist_ok=True)
                shutil.copyfile(src, tmp.calibration_file(t))
        Manifest(seqs, str(doc["dataset"].get("robot") or doc["robot"]["name"]), "bundle").write(tmp.manifest)
        keep = tmp.root / RECORD_DIR
        keep.mkdir()
        for rel in ("bundle.json", SUMS, "README.md"):
            if (folder / rel).is_file():
                shutil.copyfile(folder / rel, keep / rel)
        if (folder / "board").is_dir():
            shutil.copytree(folder / "board", keep / "board")
        record(tmp, ident)
        if layout.root.exists():
            remove_atomic(layout.root)  # replace (checked above) or an empty folder
        os.replace(tmp.root, layout.root)
    except BaseException:
        shutil.rmtree(tmp.root, ignore_errors=True)
        raise
    _stamp_calibrations(layout, doc)
    return ImportResult(layout, doc, True, commands)


def _stamp_calibrations(layout: Layout, doc: dict[str, Any]) -> None:
    """The stamps ``calibrate`` would have written for the bundle's calibrations (made from the Train
    split files, the bundle's robot and calibration settings), so that a fit takes them as current and
    ``calibrate`` with the same settings finds them up to date."""
    from skidbench.pipeline.calibrate.calibration import CALIBRATION_SCHEMA, calibration_stamp, train_files

    for t in doc["dataset"]["terrains"]:
        path = layout.calibration_file(t)
        settings = (doc.get("calibration_settings") or {}).get(t)
        if not path.is_file():
            continue
        stamp = calibration_stamp(layout, t)
        made_of = {"robot": doc["robot"]["spec"], "settings": settings, "schema": CALIBRATION_SCHEMA}
        key = stamp.key(train_files(layout, t), made_of)
        if not stamp.is_fresh(key):
            stamp.record(key, [path], {"imported_from": str(doc["dataset"].get("name"))})


def next_commands(doc: dict[str, Any], name: str) -> list[str]:
    """What to run on an imported dataset: evaluate (the built-in models), compare, score."""
    robot = doc["robot"]["name"]
    ds = f"source=bundle dataset={name}" + (f" robot={robot}" if robot != "jackal" else "")
    proto = doc["protocol"]["inputs_written"]
    return [
        f"skidbench evaluate {ds}" + ("" if proto == "commanded" else f" inputs={proto}"),
        f"skidbench compare {ds}",
        f"skidbench score {name} --predictions <file> inputs={proto}",
    ]


def describe_export(res: ExportResult) -> str:
    return (
        f"export: {res.folder}: {res.files} files, {res.bytes / 1e6:.1f} MB; boards {', '.join(res.boards)}; "
        f"model inputs under inputs={res.inputs} ({res.sequences} tables); check with "
        f"`sha256sum -c SHA256SUMS` in it, import with `skidbench import {res.folder}`"
    )


def describe_import(res: ImportResult, bundle: Path) -> str:
    what = "imported" if res.imported else "already imported (same content); nothing changed"
    lines = [
        f"import: {bundle}: every checksum verified; {what} as dataset {res.layout.dataset} -> "
        f"{res.layout.root}",
        "next:",
        *[f"  {c}" for c in res.commands],
    ]
    return "\n".join(lines)
