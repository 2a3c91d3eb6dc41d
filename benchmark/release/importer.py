"""``skidbench import <dir> [bundle.answers=<private>]``: a bundle verified and made a dataset
(pipeline/datasets/imported.py says what its folder holds).

Import checks every file of the bundle (and of the private half, when given) against its ``SHA256SUMS``
before anything is written (a missing, changed or unlisted file is one line naming it), checks that the
private half answers this public half (its ``answers.json`` names the sha256 of the public
``SHA256SUMS``), and builds ``<out_root>/<name>/`` in a temporary folder renamed into place: nothing is
half-written. The dataset's identity is the content: the public half's checksum manifest and, when
imported with them, the answers'.

The public half alone makes a dataset with Train (and the CV/LD model inputs and window list, under its
``bundle/`` record): a lab fits there and checks a predictions file's shape (``score.check=true``);
``evaluate`` and ``score`` refuse it, the test truth being withheld. With the private half (the
maintainer's) or an open release, ``evaluate source=bundle`` refits the same built-in models on the same
bytes and scores them the same way, so its board equals the exported one cell for cell.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from skidbench.benchmark.release.bundle import SUMS, BundleError, read_doc, release_of, verify
from skidbench.benchmark.release.halves import ANSWERS, OPEN, WINDOWS, read_answers
from skidbench.pipeline.core.io import sha256_file
from skidbench.pipeline.core.layout import Layout, default_out_root, fingerprint_of, remove_atomic
from skidbench.pipeline.core.manifest import Manifest
from skidbench.pipeline.core.manifest import Sequence as ManifestSequence
from skidbench.pipeline.datasets.identity import DatasetIdentity, read_record, record
from skidbench.pipeline.datasets.imported import RECORD_DIR, SOURCE


@dataclass
class ImportResult:
    layout: Layout
    doc: dict[str, Any]
    imported: bool  # False: the same bundle was already imported there
    commands: list[str] = field(default_factory=list)
    has_answers: bool = True


def _safe_rel(folder: Path, rel: str) -> Path:
    """``folder / rel`` for a relative path that stays inside ``folder`` (BundleError otherwise)."""
    path = (folder / rel).resolve()
    if not str(path).startswith(str(folder.resolve()) + os.sep):
        raise BundleError(f"{folder / 'bundle.json'}: file {rel!r} points outside the bundle")
    return path


def _answers(folder: Path, doc: dict[str, Any], answers: Path | None) -> tuple[Path | None, dict | None]:
    """The private half's folder and ``answers.json``, verified and checked to answer ``folder``."""
    if answers is None:
        return None, None
    if release_of(doc) == OPEN:
        raise BundleError(
            f"bundle.answers={answers}: {folder} is an open release (its test truth is in it); import it "
            "without bundle.answers"
        )
    answers = Path(answers).expanduser().resolve()
    verify(answers, ANSWERS)
    ans = read_answers(answers, BundleError)
    want = sha256_file(folder / SUMS)
    if ans.get("public_sha256sums") != want:
        raise BundleError(
            f"{answers / ANSWERS}: the answers of another public half (SHA256SUMS sha256 "
            f"{str(ans.get('public_sha256sums'))[:16]}...), not of {folder} ({want[:16]}...)"
        )
    return answers, ans


def import_bundle(
    folder: Path, out_root: Path, name: str | None = None, replace: bool = False, answers: Path | None = None
) -> ImportResult:
    """Verifies the bundle at ``folder`` (and the private half ``answers``) and makes the dataset
    ``<out_root>/<name>`` (default name: the exported dataset's). Importing the same content again changes
    nothing; a folder holding another dataset is refused unless ``replace``."""
    folder = Path(folder).expanduser().resolve()
    sums = verify(folder)
    doc = read_doc(folder)
    ans_folder, ans = _answers(folder, doc, answers)
    name = str(name or doc["dataset"]["name"])
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", name):
        raise BundleError(f"dataset name {name!r}: use letters, digits, '_', '.', '-' (set bundle.name=...)")
    key = {"source": SOURCE, "sha256": sha256_file(folder / SUMS)}
    if ans_folder is not None:
        key["answers"] = sha256_file(ans_folder / SUMS)
    ident = DatasetIdentity(name, SOURCE, str(folder), fingerprint_of(key))
    layout = Layout(Path(out_root), name)
    has_answers = release_of(doc) == OPEN or ans is not None
    commands = next_commands(doc, name, Path(out_root), has_answers)
    have = read_record(layout)
    if have is not None and have.get("fingerprint") == ident.fingerprint:
        _stamp_calibrations(layout, doc)  # what an interrupted import may not have finished
        return ImportResult(layout, doc, False, commands, has_answers)
    if layout.root.exists() and any(layout.root.iterdir()) and not replace:
        what = f"{have.get('source')} {have.get('root')}" if have else "other files"
        raise BundleError(
            f"{layout.root}: dataset {name!r} already holds {what}; import under another name "
            "(bundle.name=<name>) or set source.replace=true to replace it"
        )
    tmp = Layout(layout.out_root, f".tmp-import-{name}.{os.getpid()}")
    shutil.rmtree(tmp.root, ignore_errors=True)
    tmp.root.mkdir(parents=True)
    try:
        _build(tmp, layout, folder, doc, sums, ans_folder, ans)
        record(tmp, ident)
        if layout.root.exists():
            remove_atomic(layout.root)  # replace (checked above) or an empty folder
        os.replace(tmp.root, layout.root)
    except BaseException:
        shutil.rmtree(tmp.root, ignore_errors=True)
        raise
    _stamp_calibrations(layout, doc)
    return ImportResult(layout, doc, True, commands, has_answers)


def _build(tmp: Layout, layout: Layout, folder: Path, doc: dict, sums: dict, ans_folder, ans) -> None:
    """The dataset's files in ``tmp``: the split files the bundle (and its answers) hold, the card, the
    calibrations, the manifest and the bundle's record."""
    where = {s["name"]: (folder, s["file"]) for s in doc["sequences"] if s.get("file")}
    if ans is not None:
        ans_sums = verify(ans_folder, ANSWERS)
        for s in ans["sequences"]:
            if s["file"] not in ans_sums:
                raise BundleError(f"{ans_folder / ANSWERS}: sequence {s['name']}'s file is not in its {SUMS}")
            where[s["name"]] = (ans_folder, s["file"])
    seqs = []
    for s in doc["sequences"]:
        if s["name"] not in where:
            continue  # a withheld CV/LD sequence: its inputs only (the record below)
        src_folder, rel = where[s["name"]]
        if src_folder == folder and rel not in sums:
            raise BundleError(f"{folder / 'bundle.json'}: sequence {s['name']}'s file {rel} is not in {SUMS}")
        out = tmp.split_file(s["terrain"], s["split"], s["name"])
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(_safe_rel(src_folder, rel), out)
        final = layout.split_file(s["terrain"], s["split"], s["name"])
        seqs.append(ManifestSequence(s["name"], s["terrain"], s["split"], os.path.relpath(final, layout.raw)))
    if (folder / "card.md").is_file():
        tmp.splits.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(folder / "card.md", tmp.splits / "card.md")
    for t in doc["dataset"]["terrains"]:
        src = folder / "calibration" / f"{t}.json"
        if src.is_file():
            tmp.calibration.mkdir(exist_ok=True)
            shutil.copyfile(src, tmp.calibration_file(t))
    Manifest(seqs, str(doc["dataset"].get("robot") or doc["robot"]["name"]), "bundle").write(tmp.manifest)
    keep = tmp.root / RECORD_DIR
    keep.mkdir()
    for rel in ("bundle.json", SUMS, "README.md", WINDOWS):
        if (folder / rel).is_file():
            shutil.copyfile(folder / rel, keep / rel)
    for sub in ("board", "inputs"):
        if (folder / sub).is_dir():
            shutil.copytree(folder / sub, keep / sub)
    if ans is not None:
        shutil.copyfile(ans_folder / ANSWERS, keep / ANSWERS)


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


def next_commands(
    doc: dict[str, Any], name: str, out_root: Path | None = None, answers: bool = True
) -> list[str]:
    """What to run on an imported dataset, runnable as printed (``out_root=`` when it is not the default;
    ``<file>``, ``<url>``, ``<who>``: yours): with the test answers, evaluate (the built-in models), compare
    and score a submission; without, check a predictions file's shape."""
    robot = doc["robot"]["name"]
    root = ""
    if out_root is not None and Path(out_root).expanduser().absolute() != default_out_root().absolute():
        root = f" out_root={shlex.quote(str(Path(out_root).expanduser().absolute()))}"
    ds = f"source=bundle dataset={name}" + (f" robot={robot}" if robot != "jackal" else "") + root
    protos = list((doc["protocol"].get("inputs") or {}).keys()) or [doc["protocol"]["inputs_written"]]
    proto = "commanded" if "commanded" in protos else protos[0]
    given = "" if proto == "commanded" else f" inputs={proto}"
    if not answers:
        return [f"skidbench score {name} --predictions <file>{given} score.check=true{root}"]
    return [
        f"skidbench evaluate {ds}{given}",
        f"skidbench compare {ds}{given}",
        f"skidbench score {name} --predictions <file>{given} score.link=<url> score.submitter=<who>{root}",
    ]


def describe_import(res: ImportResult, bundle: Path) -> str:
    what = "imported" if res.imported else "already imported (same content); nothing changed"
    truth = (
        ""
        if res.has_answers
        else "; the CV/LD ground truth is withheld (the public half): fit on Train "
        "and check predictions files here, the maintainer scores them"
    )
    lines = [
        f"import: {bundle}: every checksum verified; {what} as dataset {res.layout.dataset} -> "
        f"{res.layout.root}{truth}",
        "next:",
        *[f"  {c}" for c in res.commands],
    ]
    return "\n".join(lines)
