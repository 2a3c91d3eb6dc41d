"""What a released benchmark gives away and what it keeps (docs/publishing.md).

``skidbench export <dataset> <dir>`` writes, by default (``bundle.release=withheld``), two bundles, each with
its own ``SHA256SUMS``::

    <dir>/public/     to publish: what a lab needs to fit a model, run it and check its predictions file;
                      no test answer
        splits/<terrain>/train/<seq>.parquet                 Train, with its ground truth
        inputs/<protocol>/<terrain>/<split>/<seq>.parquet    the model inputs of every protocol the data
                                                             allow (``INPUT_COLUMNS``), every sequence: CV
                                                             and LD appear only here
        windows.parquet                                      the windows the board scores (terrain, split,
                                                             sequence, horizon_s, start, end, t0, t1): made
                                                             from the clock and the ground truth's validity
        bundle.json, README.md, card.md, calibration/, board/, SHA256SUMS
    <dir>/private/    the maintainer keeps it: the CV/LD answers
        splits/<terrain>/<cv|ld>/<seq>.parquet               the CV/LD split files, byte for byte
        answers.json                                         the public half they answer (the sha256 of its
                                                             SHA256SUMS) and their sequences
        README.md, SHA256SUMS

A predictions file made from the public half alone has no truth to copy: no CV/LD pose, velocity or
validity column is in it (:data:`WITHHELD_COLUMNS`; the calibration is made from Train). ``bundle.release=
open`` writes one bundle, ``<dir>/``, with every split file (test truth included): for data already public
in full, whose board's external entries are then self-reported.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa

from skidbench.benchmark.release.settings import RELEASES
from skidbench.benchmark.scoring.horizon import horizon_steps
from skidbench.pipeline.core.errors import SkidbenchError
from skidbench.pipeline.core.io import (
    read_json_object,
    write_json_atomic,
    write_parquet_atomic,
    write_text_atomic,
)
from skidbench.pipeline.core.layout import Layout, split_terrains
from skidbench.pipeline.core.manifest import Manifest
from skidbench.pipeline.core.protocol import (
    INPUT_COLUMNS,
    PROTOCOL_VERSION,
    PROTOCOLS,
    TARGET_COLUMNS,
    ProtocolError,
    model_inputs,
)
from skidbench.pipeline.core.schema import read_split

WITHHELD, OPEN = RELEASES  # bundle.release's choices
PUBLIC, PRIVATE = "public", "private"
TEST_SPLITS = ("cv", "ld")
ANSWERS = "answers.json"
ANSWERS_FORMAT = "skidbench-answers"
WINDOWS = "windows.parquet"
#: ``<ds>/release.json``: what the dataset's last export released (publish says whether its truth is public)
RELEASE_RECORD = "release.json"
#: the split columns a public half never holds for a CV/LD sequence: the ground truth (pose, body
#: velocities and their validity); everything a model may be given is in its inputs tables instead
WITHHELD_COLUMNS = TARGET_COLUMNS
WINDOW_COLUMNS = ("terrain", "split", "sequence", "horizon_s", "start", "end", "t0", "t1")
#: the protocols a lab can predict under from a public half: not ``state``, whose windows start from the
#: ground truth's state (the past body velocity), which the public half withholds
PUBLIC_PROTOCOLS = tuple(p for p in PROTOCOLS if p != "state")


def public_files(layout: Layout, manifest: Manifest, release: str) -> list[Path]:
    """The split files a bundle of ``release`` carries: every one (``open``), or Train's (``withheld``)."""
    files = layout.split_files(manifest)
    if release == OPEN:
        return files
    return [p for p in files if p.parent.name not in TEST_SPLITS]


def private_files(layout: Layout, manifest: Manifest) -> list[Path]:
    """The CV/LD split files: the answers a withheld release keeps."""
    return [p for p in layout.split_files(manifest) if p.parent.name in TEST_SPLITS]


def write_inputs(
    robot: Any, calibrations: Any, layout: Layout, manifest: Manifest, dest: Path, error: type[SkidbenchError]
) -> dict[str, list[str]]:
    """``inputs/<protocol>/<terrain>/<split>/<seq>.parquet``: :func:`model_inputs` of every split file
    under every public protocol the terrain allows (:data:`PUBLIC_PROTOCOLS`: ``commanded`` always;
    ``response`` when calibrate identified
    the terrain's wheel response; ``measured`` when every sequence has encoders). Returns ``{protocol:
    [terrains]}``; ``error`` when a split file cannot be read."""
    from skidbench.pipeline.calibrate.calibration import response_for

    written: dict[str, list[str]] = {}
    for terrain in split_terrains(manifest):
        files = layout.require_split_files(manifest, terrain, None, error)
        tables = []
        for path in files:
            df, meta = read_split(path)
            tables.append((path, str(meta.get("sequence") or path.stem), df))
        response = response_for(calibrations, terrain)
        for protocol in PUBLIC_PROTOCOLS:
            if protocol == "response" and response is None:
                continue
            try:
                made = [
                    (p, seq, model_inputs(df.assign(sequence=seq), protocol, robot, response))
                    for p, seq, df in tables
                ]
            except ProtocolError:  # measured without encoders: not a protocol of this terrain
                continue
            for path, seq, table in made:
                write_parquet_atomic(
                    pa.Table.from_pandas(table[list(INPUT_COLUMNS)], preserve_index=False),
                    dest / "inputs" / protocol / path.relative_to(layout.splits),
                    {
                        "sequence": seq,
                        "terrain": terrain,
                        "split": path.parent.name,
                        "inputs": protocol,
                        "protocol_version": PROTOCOL_VERSION,
                        "robot": robot.name,
                    },
                )
            written.setdefault(protocol, []).append(terrain)
    return {p: written[p] for p in PROTOCOLS if p in written}


def window_list(t: np.ndarray, valid: np.ndarray, horizon_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) of the windows of ``horizon_s`` that evaluate scores in one sequence: a full horizon
    of valid ground truth (benchmark/scoring/horizon.py ``window_errors``, before its minimum distance and
    rotation, which need the pose)."""
    n = horizon_steps(t, horizon_s)
    if n < 1 or len(t) <= n:
        return np.array([], dtype=int), np.array([], dtype=int)
    starts = np.arange(len(t) - n)
    ends = starts + n
    bad = np.concatenate([[0], np.cumsum(~np.asarray(valid, dtype=bool))])
    keep = (bad[ends + 1] - bad[starts]) == 0
    return starts[keep], ends[keep]


def write_windows(layout: Layout, manifest: Manifest, horizons: list[float], dest: Path) -> int:
    """``windows.parquet``: every CV/LD window of every horizon (:data:`WINDOW_COLUMNS`); its row count."""
    frames = []
    for path in private_files(layout, manifest):
        df, meta = read_split(path)
        t = df["t"].to_numpy(float)
        for h in horizons:
            starts, ends = window_list(t, df["valid"].to_numpy(bool), float(h))
            frames.append(
                pd.DataFrame(
                    {
                        "terrain": path.parent.parent.name,
                        "split": path.parent.name,
                        "sequence": str(meta.get("sequence") or path.stem),
                        "horizon_s": float(h),
                        "start": starts,
                        "end": ends,
                        "t0": t[starts],
                        "t1": t[ends],
                    }
                )
            )
    table = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=list(WINDOW_COLUMNS))
    write_parquet_atomic(
        pa.Table.from_pandas(table[list(WINDOW_COLUMNS)], preserve_index=False),
        dest / WINDOWS,
        {"horizons": [float(h) for h in horizons]},
    )
    return len(table)


def answers_doc(dataset: str, public_sums_sha256: str, sequences: list[dict[str, Any]], written_by) -> dict:
    """``answers.json`` of a private half: the public half it answers and the sequences it holds."""
    return {
        "format": ANSWERS_FORMAT,
        "version": 1,
        "dataset": dataset,
        "public_sha256sums": public_sums_sha256,
        "sequences": sequences,
        "written_by": written_by,
    }


def write_private_readme(folder: Path, dataset: str) -> None:
    write_text_atomic(
        folder / "README.md",
        "\n".join(
            [
                f"# skidbench: the test answers of {dataset}",
                "",
                "The CV and LD split files (ground-truth pose and velocities) of the public bundle beside",
                "this folder. Keep them: do not publish them. Score a submission with them:",
                "`skidbench import <public> bundle.answers=<this folder>` makes a dataset with its answers,",
                "then",
                f"`skidbench score {dataset} --predictions <file> score.link=... score.submitter=...`.",
                "Check it: `sha256sum -c SHA256SUMS`.",
                "",
            ]
        ),
    )


def read_answers(folder: Path, error: type[SkidbenchError]) -> dict[str, Any]:
    """``<folder>/answers.json``; ``error`` (one line) when it is missing or not a private half's."""
    path = Path(folder) / ANSWERS
    doc = read_json_object(path, error, f"{folder} is not the private half of a skidbench bundle")
    if not isinstance(doc, dict) or doc.get("format") != ANSWERS_FORMAT:
        raise error(f"{path}: not the answers of a skidbench bundle")
    return doc


def write_answers(folder: Path, doc: dict[str, Any]) -> None:
    write_json_atomic(folder / ANSWERS, doc)


def dataset_title(robot: str, terrains: list[str], source: Any) -> str:
    """The dataset's title on its card and page: ``Jackal on asphalt, grass and tile (simulated)``."""
    where = ", ".join(terrains[:-1]) + f" and {terrains[-1]}" if len(terrains) > 1 else "".join(terrains)
    kind = {"sim": " (simulated)", "bundle": ""}.get(str(source), f" ({source} recordings)")
    return f"{robot[:1].upper()}{robot[1:]} on {where}{kind}"


def public_card(layout: Layout, manifest: Manifest, robot: Any, release: str, licence: str) -> str:
    """The card a release publishes (Markdown): its title, the robot and its constants, per split and
    terrain the sequences, their duration and, where the release holds the ground truth (Train; every split
    of an open release), the paper's Table I statistics (pipeline/splits/card.py ``table_stats``); the
    licence. No CV/LD statistic of a withheld release: they are computed from its ground truth."""
    from skidbench.pipeline.datasets.identity import read_record
    from skidbench.pipeline.splits.card import table_stats

    rec = read_record(layout) or {}
    terrains = split_terrains(manifest)
    groups: dict[tuple[str, str], list[tuple[pd.DataFrame, float]]] = {}
    for path in layout.split_files(manifest):
        df, meta = read_split(path)
        groups.setdefault((path.parent.name, path.parent.parent.name), []).append(
            (df, float(meta.get("rate_hz") or 30.0))
        )
    rows = []
    order = {"train": 0, "cv": 1, "ld": 2}
    for (split, terrain), items in sorted(groups.items(), key=lambda kv: (order.get(kv[0][0], 9), kv[0][1])):
        frames = [df for df, _ in items]
        seconds = sum(len(df) / rate for df, rate in items)
        if release == WITHHELD and split in TEST_SPLITS:
            stats = ["withheld"] * 3
        else:
            s = table_stats(frames, robot, items[0][1])
            stats = [f"{s['distance_m']:.1f}", f"{s['lin_mean']:.2f}", f"{s['ang_mean']:.1f}"]
        rows.append(f"| {split} | {terrain} | {len(frames)} | {seconds:.0f} | " + " | ".join(stats) + " |")
    total = sum(len(df) / rate for items in groups.values() for df, rate in items)
    return "\n".join(
        [
            f"# {dataset_title(robot.name, terrains, rec.get('source'))}",
            "",
            f"Robot: {robot.name} (wheel radius {robot.wheel_radius:g} m, track width "
            f"{robot.track_width:g} m, mass {robot.mass:g} kg). Terrains: {', '.join(terrains)}. "
            f"{len(layout.split_files(manifest))} sequences, {total / 60:.1f} min. "
            f"Licence of the data: {licence}.",
            "",
            "| Split | Terrain | Sequences | Duration (s) | Distance (m) | Lin. vel. mean (m/s) | "
            "Ang. vel. mean (deg/s) |",
            "|---|---|---|---|---|---|---|",
            *rows,
            "",
            "Distance and velocities over the valid ground-truth samples (pipeline/splits/card.py)"
            + ("; CV and LD withheld with their ground truth." if release == WITHHELD else "."),
            "",
        ]
    )
