"""A released benchmark: ``skidbench export <dataset> <dir>`` writes a dataset and its board as bundles
(folders of plain files), ``skidbench import <dir>`` (benchmark/release/importer.py) verifies one and
makes a dataset of it.

A bundle (format ``skidbench-bundle`` version :data:`BUNDLE_VERSION`)::

    bundle.json                    what it is: the release (``withheld``: the public half of
                                   benchmark/release/halves.py; ``open``), the dataset (name, source,
                                   identity), the robot (name and constants), every sequence (terrain,
                                   split, rows, seconds, its split file when the bundle holds it), the
                                   protocols whose inputs it holds, the protocol and metric versions and
                                   the settings the board was scored with, the calibration settings, the
                                   licence and provenance of the source data, the skidbench version and
                                   commit that wrote it
    SHA256SUMS                     the sha256 of every other file (``sha256sum -c SHA256SUMS`` checks it)
    README.md                      what is in it and how to use it
    card.md                        the dataset card (benchmark/release/halves.py ``public_card``)
    splits/<terrain>/<split>/<seq>.parquet   the split files it holds, byte for byte (pipeline/core/schema.py)
    calibration/<terrain>.json     the effective wheel radius and track width and the wheel response
    board/<protocol>.csv|json      the board of each protocol evaluated, every row with its provenance
                                   (benchmark/board/boards.py)
    inputs/<protocol>/<terrain>/<split>/<seq>.parquet   the exact table a model is run on under each
                                   protocol the data allow: pipeline/core/protocol.py ``model_inputs``,
                                   the columns ``INPUT_COLUMNS`` only, never the targets, the pose or the
                                   encoders
    windows.parquet                the windows the board scores

Export builds every bundle in a temporary sibling folder renamed into place when complete: nothing is
half-written.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import importlib.metadata as md
import json
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from skidbench.benchmark.board import boards as brd
from skidbench.benchmark.board.selection import results_of
from skidbench.benchmark.release import halves as hv
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.tracking import store as trk
from skidbench.pipeline.core.errors import SkidbenchError
from skidbench.pipeline.core.io import read_json_object, sha256_file, write_json_atomic, write_text_atomic
from skidbench.pipeline.core.layout import Layout, split_terrains
from skidbench.pipeline.core.manifest import Manifest
from skidbench.pipeline.core.protocol import INPUT_COLUMNS, PROTOCOL_VERSION
from skidbench.pipeline.core.schema import read_split
from skidbench.pipeline.datasets.identity import read_record
from skidbench.pipeline.datasets.imported import RECORD_DIR
from skidbench.pipeline.runner import environment

BUNDLE_FORMAT = "skidbench-bundle"
#: 2: the release (withheld test truth: public and private halves), every protocol's inputs, the windows
BUNDLE_VERSION = 2
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


def verify(folder: Path, doc: str = "bundle.json") -> dict[str, str]:
    """Checks every file of a bundle (or of a private half: ``doc`` its ``answers.json``) against
    ``SHA256SUMS``: BundleError (one line naming the file) for a listed file that is missing or whose
    sha256 differs, and for a file the list does not hold. Returns the list."""
    folder = Path(folder)
    if not folder.is_dir():
        raise BundleError(f"{folder}: no such folder")
    sums = read_sums(folder)
    if doc not in sums:
        what = "bundle" if doc == "bundle.json" else "bundle's private half"
        raise BundleError(f"{folder / SUMS}: does not list {doc}; not a skidbench {what}")
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


def release_of(doc: dict[str, Any]) -> str:
    """A bundle's release: ``withheld`` (a public half) or ``open`` (a bundle of version 1: open)."""
    return str(doc.get("release") or hv.OPEN)


def read_doc(folder: Path) -> dict[str, Any]:
    """``<folder>/bundle.json``; BundleError (one line) when it is missing, unreadable or newer."""
    path = folder / "bundle.json"
    doc = read_json_object(path, BundleError, f"{folder} is not a skidbench bundle")
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


def read_bundle_doc(folder: Path) -> dict[str, Any] | None:
    """``<folder>/bundle.json`` (a bundle, or an imported dataset's ``bundle/`` record), else None."""
    with contextlib.suppress(OSError, ValueError):
        doc = json.loads((Path(folder) / "bundle.json").read_text())
        return doc if isinstance(doc, dict) and doc.get("format") == BUNDLE_FORMAT else None
    return None


# -- export ------------------------------------------------------------------------------------------
@dataclass
class ExportResult:
    folder: Path
    release: str
    files: int
    bytes: int
    boards: list[str]
    inputs: dict[str, list[str]]
    windows: int


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
    """What ``export`` reads of its config (the app builds it): the robot (``robot``) and calibrations the
    inputs are made with, and of the ``bundle`` section (:class:`~.settings.ExportBundle`) the release
    (withheld or open), the source data's licence and provenance (None: unset)."""

    robot: Any  # pipeline.core.robot.Robot
    calibrations: Any  # pipeline.calibrate.calibration.Calibrations
    release: str
    licence: str | None
    provenance: str | None


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


def _sequences(layout: Layout, manifest: Manifest, held: set[Path]) -> list[dict[str, Any]]:
    """Every train/cv/ld sequence: its rows and seconds, and its split file when ``held`` has it (None:
    withheld)."""
    out = []
    for seq in manifest.sequences:
        if seq.category not in ("train", *hv.TEST_SPLITS):
            continue
        path = layout.split_file(seq.terrain, seq.category, seq.name)
        df, meta = read_split(path)
        t = df["t"].to_numpy(float)
        out.append(
            {
                "name": seq.name,
                "terrain": seq.terrain,
                "split": seq.category,
                "file": path.relative_to(layout.root).as_posix() if path in held else None,
                "rows": int(len(df)),
                "duration_s": float(t[-1] - t[0]) if len(t) > 1 else 0.0,
                "rate_hz": meta.get("rate_hz"),
            }
        )
    return out


def _check_exportable(layout: Layout, dest: Path) -> tuple[Manifest, list[str]]:
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise BundleError(f"{dest}: exists and is not an empty folder; export to a new folder")
    if not layout.manifest.is_file():
        raise BundleError(
            f"{layout.root}: no dataset here (no {layout.manifest}); `skidbench datasets` lists them"
        )
    manifest = Manifest.read(layout.manifest)
    terrains = split_terrains(manifest)
    if not terrains:
        raise BundleError(f"{layout.manifest}: no train/cv/ld sequences; nothing to export")
    layout.require_split_files(manifest, None, None, BundleError)
    for t in terrains:
        if not layout.calibration_file(t).is_file():
            raise BundleError(
                f"{layout.calibration_file(t)}: missing; run `skidbench calibrate` (a bundle ships the "
                "calibration every fit is built with)"
            )
    return manifest, terrains


def export_bundle(s: ExportSettings, layout: Layout, dest: Path, tracker: trk.Tracker | None) -> ExportResult:
    """Writes ``layout``'s dataset to ``dest`` (a new or empty folder): its public and private halves
    (``<dest>/public``, ``<dest>/private``: benchmark/release/halves.py), or with ``release=open`` one
    bundle with every split file; built in a temporary sibling folder renamed into place when complete."""
    dest = Path(dest).expanduser().absolute()
    manifest, terrains = _check_exportable(layout, dest)
    rec = read_record(layout) or {}
    lic = licence_of(s.licence, str(rec.get("source", "?")))
    ident = (tracker.dataset_id if tracker is not None else None) or rec.get("fingerprint")
    experiment = tracker.experiment_name if tracker is not None else None
    boards = brd.all_boards(results_of(layout, str(ident or "") or None, experiment))
    if not boards:
        raise BundleError(
            f"{layout.root}: no `skidbench evaluate` run of dataset {layout.dataset} in its results table "
            f"({layout.root / 'results'}); run it first (a bundle ships the board)"
        )
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".tmp-export-{dest.name}.{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        public = tmp if s.release == hv.OPEN else tmp / hv.PUBLIC
        doc, n_windows = _write_public(s, layout, manifest, terrains, rec, boards, lic, public)
        if s.release == hv.WITHHELD:
            _write_private(layout, manifest, tmp / hv.PRIVATE, public, doc["written_by"])
        if dest.exists():
            dest.rmdir()  # empty (checked above)
        os.replace(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    write_json_atomic(layout.root / hv.RELEASE_RECORD, {"release": s.release, **doc["written_by"]})
    n_files = sum(1 for p in dest.rglob("*") if p.is_file())
    size = sum(p.stat().st_size for p in dest.rglob("*") if p.is_file())
    return ExportResult(dest, s.release, n_files, size, list(boards), doc["protocol"]["inputs"], n_windows)


def _write_public(s, layout, manifest, terrains, rec, boards, lic, out: Path) -> tuple[dict[str, Any], int]:
    """The bundle a lab downloads (all of it for an open release); its bundle.json and window count."""
    out.mkdir(parents=True)
    held = hv.public_files(layout, manifest, s.release)
    for p in held:
        target = out / p.relative_to(layout.root)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(p, target)
    write_text_atomic(out / "card.md", hv.public_card(layout, manifest, s.robot, s.release, lic))
    calib_settings = {}
    for t in terrains:
        (out / "calibration").mkdir(exist_ok=True)
        shutil.copyfile(layout.calibration_file(t), out / "calibration" / f"{t}.json")
        calib_settings[t] = _calibration_settings(layout, t)
    for b in boards.values():
        brd.write_board(b, out / "board", {"dataset": layout.dataset, "dataset_id": rec.get("fingerprint")})
    inputs = hv.write_inputs(s.robot, s.calibrations, layout, manifest, out, BundleError)
    first = next(iter(boards.values()))
    horizons = [float(h) for h in (first.settings.get("horizons") or [first.horizon])]
    n_windows = hv.write_windows(layout, manifest, horizons, out)
    doc = _bundle_doc(s, layout, rec, manifest, boards, lic, calib_settings, set(held), inputs)
    write_json_atomic(out / "bundle.json", doc)
    write_text_atomic(out / "README.md", _readme(doc))
    write_sums(out)
    return doc, n_windows


def _write_private(layout: Layout, manifest: Manifest, out: Path, public: Path, written_by) -> None:
    """The answers the maintainer keeps: the CV/LD split files and ``answers.json`` naming ``public``."""
    out.mkdir(parents=True)
    seqs = []
    for p in hv.private_files(layout, manifest):
        rel = p.relative_to(layout.root)
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(p, out / rel)
        seqs.append(
            {"name": p.stem, "terrain": p.parent.parent.name, "split": p.parent.name, "file": rel.as_posix()}
        )
    hv.write_answers(out, hv.answers_doc(layout.dataset, sha256_file(public / SUMS), seqs, written_by))
    hv.write_private_readme(out, layout.dataset)
    write_sums(out)


def _bundle_doc(
    s: ExportSettings, layout, rec, manifest, boards, lic, calib_settings, held, inputs
) -> dict[str, Any]:
    robot = s.robot
    first = next(iter(boards.values()))
    return {
        "format": BUNDLE_FORMAT,
        "version": BUNDLE_VERSION,
        "release": s.release,
        "dataset": {
            "name": layout.dataset,
            "source": rec.get("source"),
            "fingerprint": rec.get("fingerprint"),
            "terrains": split_terrains(manifest),
            "robot": manifest.robot,
        },
        "robot": {"name": robot.name, "spec": json.loads(json.dumps(robot.to_dict(), default=str))},
        "sequences": _sequences(layout, manifest, held),
        "protocol": {
            "version": PROTOCOL_VERSION,
            "input_columns": list(INPUT_COLUMNS),
            "inputs": inputs,
            "boards": list(boards),
        },
        "windows": hv.WINDOWS,
        "metric": {
            **METRIC,
            **{
                k: first.settings.get(k) for k in ("horizons", "splits", "min_distance_m", "min_rotation_deg")
            },
            # every metric the boards hold (benchmark/scoring/metrics.py): its MLflow name, unit, definition
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
        },
        "calibration_settings": calib_settings,
        "licence": lic,
        "provenance": {
            "statement": s.provenance
            or (
                f"simulated by skidbench {_version()} (`skidbench simulate`), dataset {layout.dataset}"
                if rec.get("source") == "sim"
                else f"{rec.get('source')} data, dataset {layout.dataset}"
            ),
            "source": rec.get("source"),
            "fingerprint": rec.get("fingerprint"),
            "imported_from": (read_bundle_doc(layout.root / RECORD_DIR) or {}).get("dataset"),
        },
        "written_by": {
            "skidbench": _version(),
            "git_commit": environment.git_commit(),
            "utc": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M:%S"),
        },
    }


def _readme(doc: dict[str, Any]) -> str:
    ds, name = doc["dataset"], doc["dataset"]["name"]
    seqs = doc["sequences"]
    withheld = release_of(doc) == hv.WITHHELD
    held = [x for x in seqs if x.get("file")]
    what = (
        "The public half of the benchmark: Train with its ground truth, CV and LD as model inputs only (the "
        "test answers are withheld; the maintainer scores submissions)."
        if withheld
        else "An open release: every split file, test ground truth included (entries scored from it are "
        "self-reported)."
    )
    protos = ", ".join(doc["protocol"]["inputs"])
    return "\n".join(
        [
            f"# skidbench bundle: {name}",
            "",
            what,
            "",
            f"Robot `{doc['robot']['name']}`, terrains {', '.join(ds['terrains'])}; {len(seqs)} sequences, "
            f"{len(held)} split files here. Licence of the data: {doc['licence']}.",
            f"Provenance: {doc['provenance']['statement']}.",
            "",
            "Check it: `sha256sum -c SHA256SUMS`. Make a dataset of it: `skidbench import <this folder>`.",
            "",
            f"A model from anywhere: fit it on `splits/<terrain>/train/` (which has the targets), run it on "
            f"`inputs/<protocol>/<terrain>/<cv|ld>/<seq>.parquet` (protocols {protos}; columns "
            f"{', '.join(doc['protocol']['input_columns'])}) and write one Parquet or CSV file with columns "
            "`sequence, t, vx, vy, wz` (body velocities, m/s and rad/s, one row per input row). "
            f"`skidbench score {name} --predictions <file> score.check=true` checks its shape; "
            + (
                "send it to the maintainer with the method's name, a link to its paper or code, who "
                "submits it and a one-line description."
                if withheld
                else f"`skidbench score {name} --predictions <file> score.link=<url> "
                "score.submitter=<who>` scores it."
            ),
            "",
            f"Metric: {doc['metric']['definition']} (version {doc['metric']['version']}; horizons "
            f"{doc['metric'].get('horizons')} s, min distance {doc['metric'].get('min_distance_m')} m, min "
            f"rotation {doc['metric'].get('min_rotation_deg')} deg). The windows scored: `windows.parquet`.",
            "",
        ]
    )


def describe_export(res: ExportResult) -> str:
    inputs = ", ".join(f"{p} ({len(t)} terrains)" for p, t in res.inputs.items())
    if res.release == hv.OPEN:
        halves = f"an open release (test truth included); import with `skidbench import {res.folder}`"
    else:
        halves = (
            f"publish {res.folder / hv.PUBLIC} (no test truth), keep {res.folder / hv.PRIVATE} (the CV/LD "
            f"answers); import with `skidbench import {res.folder / hv.PUBLIC}` (+ "
            f"bundle.answers={res.folder / hv.PRIVATE} to score)"
        )
    return (
        f"export: {res.folder}: {res.files} files, {res.bytes / 1e6:.1f} MB; boards {', '.join(res.boards)}; "
        f"model inputs of {inputs}; {res.windows} windows listed; {halves}; check each with "
        "`sha256sum -c SHA256SUMS` in it"
    )
