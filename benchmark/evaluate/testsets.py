"""The test data of an evaluate: the dataset's terrains and split files (from its manifest), the test
splits' sequences and the checks that make a benchmark meaningful (a split with rows, a horizon shorter than
some sequence, a window for every score: a recording too short to score is refused with the seconds it
kept and the seconds a window needs), each failure one :class:`EvaluationError` line, raised before any
run is created: nothing is ranked."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skidbench.benchmark.errors import EvaluationError
from skidbench.benchmark.scoring.horizon import (
    MINIMUMS_AT_S,
    HorizonConfig,
    count_windows,
    horizon_steps,
    window_errors,
)
from skidbench.benchmark.scoring.predictions import Inputs, TestSequence
from skidbench.pipeline.calibrate.calibration import Calibrations, response_for
from skidbench.pipeline.core.cache import Fingerprints
from skidbench.pipeline.core.errors import SkidbenchError, one_line
from skidbench.pipeline.core.io import fingerprint_obj
from skidbench.pipeline.core.layout import Layout, split_terrains
from skidbench.pipeline.core.manifest import Manifest
from skidbench.pipeline.core.protocol import sequences_without_encoders
from skidbench.pipeline.core.schema import read_split

log = logging.getLogger(__name__)

TRAIN = "train"


def current_manifest(layout: Layout) -> Manifest:
    """The dataset's current manifest: the one source of its terrains and sequences."""
    if not layout.manifest.is_file():
        raise EvaluationError(
            f"{layout.splits}: no splits; run `skidbench split` first ({layout.manifest} is absent)"
        )
    try:
        return Manifest.read(layout.manifest)
    except SkidbenchError as exc:
        raise EvaluationError(one_line(str(exc))) from None


def split_files(
    layout: Layout, terrain: str, split: str | None, manifest: Manifest | None = None
) -> list[Path]:
    """The split files of the manifest's ``terrain``/``split`` sequences; EvaluationError if one is
    missing."""
    return layout.require_split_files(manifest or current_manifest(layout), terrain, split, EvaluationError)


def find_terrains(layout: Layout) -> list[str]:
    """The manifest's terrains with train/cv/ld sequences, sorted."""
    terrains = split_terrains(current_manifest(layout))
    if not terrains:
        raise EvaluationError(f"{layout.manifest}: no train/cv/ld sequences; nothing to evaluate")
    return terrains


def load_test_split(layout: Layout, terrain: str, split: str) -> list[TestSequence]:
    """The sequences of one test split; EvaluationError when there are none or all are empty."""
    where = layout.splits / terrain / split
    files = split_files(layout, terrain, split)
    if not files:
        raise EvaluationError(
            f"{where}: empty {split} split (no sequences) for terrain {terrain}; re-run `skidbench split`, "
            f"or leave it out with splits=[...] / terrains=[...]"
        )
    seqs = []
    for p in files:
        try:
            df, meta = read_split(p)
        except SkidbenchError as exc:
            raise EvaluationError(one_line(str(exc))) from None
        seqs.append(TestSequence(str(meta.get("sequence") or p.stem), p, df, meta))
    if all(len(s.table) == 0 for s in seqs):
        raise EvaluationError(
            f"{where}: empty {split} split (every sequence has 0 rows) for terrain {terrain}"
        )
    return seqs


def check_horizons(
    terrain: str, split: str, seqs: Sequence[TestSequence], horizons: Sequence[float],
    hcfg: HorizonConfig | None = None,
) -> None:  # fmt: skip
    """EvaluationError when a horizon is longer than every sequence of a split (no window at all), and with
    ``hcfg`` when a score of the split would have no window (:func:`check_scores`)."""
    for h in horizons:
        if not h > 0:
            raise EvaluationError(f"horizon {h} s is not positive; set horizons=[6.0]")
        if not any(len(s.table) > horizon_steps(s.table["t"].to_numpy(), h) >= 1 for s in seqs):
            longest = max(s.duration_s for s in seqs)
            raise EvaluationError(
                f"splits/{terrain}/{split}: horizon {h:g} s is longer than every sequence "
                f"(longest {longest:.1f} s); lower horizons=[...]"
            )
        if hcfg is not None:
            check_scores(f"splits/{terrain}/{split}", seqs, h, hcfg)


def check_scores(where: str, seqs: Sequence[TestSequence], horizon_s: float, hcfg: HorizonConfig) -> None:
    """EvaluationError (the numbers, the setting to change) when a score of the split has no window at
    ``horizon_s``: no stretch of valid samples as long as the horizon (too short to score: the seconds
    kept against the seconds a window needs), or no window that travels ``min_distance_m`` (the
    translational score) or turns ``min_rotation_deg`` (the rotational one). Ranking a split on a score
    with no window would rank on nothing."""
    kept = longest = 0.0
    n = trans = rot = 0
    farthest = most_turn = 0.0
    for s in seqs:
        df = s.table
        if len(df) < 2:
            continue
        t, valid = df["t"].to_numpy(float), df["valid"].to_numpy(bool)
        dt = float(np.median(np.diff(t)))
        edges = np.flatnonzero(np.diff(np.concatenate([[0], valid.astype(np.int8), [0]])))
        lengths = (edges[1::2] - edges[::2]) * dt
        kept, longest = kept + float(lengths.sum()), max(longest, float(lengths.max(initial=0.0)))
        pose = df[["x", "y", "yaw"]].to_numpy(float)
        w = window_errors(t, pose, np.zeros_like(pose), horizon_s, valid, hcfg)  # only the windows' extent
        n, trans, rot = (
            n + len(w),
            trans + int(w["rel_trans"].notna().sum()),
            rot + int(w["rel_rot"].notna().sum()),
        )
        farthest = max(farthest, float(w["distance"].max()) if len(w) else 0.0)
        most_turn = max(most_turn, float(w["rotation"].max()) if len(w) else 0.0)
    h = f"{horizon_s:g} s"
    if n == 0:
        raise EvaluationError(
            f"{where}: too short to score at the {h} horizon: {kept:.1f} s of valid recording kept in "
            f"{len(seqs)} sequence(s), the longest stretch {longest:.1f} s, and a window needs {h} of "
            "valid samples; record longer (or keep more of it), or lower horizons=[...]"
        )
    min_distance, min_rotation = hcfg.minimums(horizon_s)
    deg = math.degrees(hcfg.min_rotation_rad)
    at = "" if horizon_s == MINIMUMS_AT_S else f", {min_distance:.3g} m at {h}"
    if trans == 0:
        raise EvaluationError(
            f"{where}: no {h} window travels min_distance_m={hcfg.min_distance_m:g} m{at} ({n} window(s), "
            f"the farthest {farthest:.2f} m): the translational score has nothing to rank; record the robot "
            "driving, or lower min_distance_m"
        )
    at = "" if horizon_s == MINIMUMS_AT_S else f", {math.degrees(min_rotation):.3g} deg at {h}"
    if rot == 0:
        raise EvaluationError(
            f"{where}: no {h} window turns min_rotation_deg={deg:g} deg{at} ({n} window(s), the most "
            f"{math.degrees(most_turn):.1f} deg): the rotational score has nothing to rank; record turns, "
            "or lower min_rotation_deg"
        )


def split_fingerprint(files: Sequence[Path], root: Path) -> str:
    """Fingerprint of a set of split files: the content fingerprints recorded by the split stage in
    the file metadata when present, else the files' own content hashes."""
    fp = Fingerprints()
    return fingerprint_obj({str(Path(p).relative_to(root)): fp(p) for p in sorted(files)})


def protocol_unavailable(
    cal: Calibrations, layout: Layout, protocol: str, terrain: str, train_files: Sequence[Path],
    tests: dict[str, list[TestSequence]], inputs_of: dict[str, Inputs],
) -> list[str]:  # fmt: skip
    """Checks the protocol can drive the models on ``terrain``: sets ``inputs_of[terrain]``, drops from
    ``tests`` the test splits it cannot drive (``measured`` on a split without encoders) and returns one
    line per (terrain, split) skipped (the whole terrain: no response identified, no Train encoders). ``cal``:
    the calibrations (the response, and the spec sheet's robot the inputs are converted with)."""
    where = f"{layout.splits / terrain}"
    response = None
    if protocol == "response":
        response = response_for(cal, terrain)
        if response is None:
            return [f"inputs=response: {where}: no wheel response identified (no wheel encoders in its Train "
                    "split, see `skidbench calibrate`); terrain skipped under this protocol"]  # fmt: skip
    if protocol == "measured":
        for p in train_files:
            df, _ = read_split(p)
            if sequences_without_encoders(df):
                return [
                    f"inputs=measured: {p}: no wheel encoders; terrain {terrain} skipped under this protocol"
                ]
        lines = []
        for split in list(tests):
            lacking = [s.name for s in tests[split] if len(s.table) and sequences_without_encoders(s.table)]
            if lacking:
                lines.append(f"inputs=measured: {where}/{split}: no wheel encoders in {lacking[0]}"
                             f"{f' (and {len(lacking) - 1} more)' if len(lacking) > 1 else ''}; "
                             "split skipped under this protocol")  # fmt: skip
                del tests[split]
        if not tests:
            return lines
        inputs_of[terrain] = Inputs(protocol, cal.spec, None)
        return lines
    inputs_of[terrain] = Inputs(protocol, cal.spec, response)
    return []


@dataclass
class EvaluationData:
    """The test splits an evaluate scores, checked before anything is logged: the terrains the protocol
    can drive, their test sequences per split, their split files (Train and test: the fingerprint's), the
    inputs that drive the models, and a line per (terrain, split) skipped under the protocol."""

    terrains: list[str]
    tests: dict[str, dict[str, list[TestSequence]]]
    files_of: dict[str, list[Path]]
    inputs_of: dict[str, Inputs]
    skipped: list[str]


def load_evaluation_data(
    layout: Layout, cal: Calibrations, terrains: list[str] | None, splits: Sequence[str],
    horizons: Sequence[float], protocol: str, hcfg: HorizonConfig | None = None,
) -> EvaluationData:  # fmt: skip
    """The test splits of ``terrains`` (None: every terrain of the dataset) under ``protocol``, each checked
    against the horizons and, with ``hcfg``, for a window of every score (and its windows per horizon
    logged); EvaluationError (one line) for a terrain the dataset lacks or an empty Train split."""
    found = find_terrains(layout)
    if terrains is None:
        terrains = found
    missing = [t for t in terrains if t not in found]
    if missing:
        raise EvaluationError(f"{layout.manifest}: no sequences of terrain(s) {missing}; it has {found}")
    data = EvaluationData([], {}, {}, {}, [])
    for terrain in terrains:
        train_files = split_files(layout, terrain, TRAIN)
        if not train_files:
            raise EvaluationError(
                f"{layout.splits / terrain / TRAIN}: empty train split for terrain {terrain}"
            )
        data.tests[terrain] = {}
        for split in splits:
            seqs = load_test_split(layout, terrain, split)
            check_horizons(terrain, split, seqs, horizons, hcfg)
            for h in horizons:  # short sequences: say how many windows each horizon has (compare shows n)
                n_win, n_seq, short = count_windows([s.table for s in seqs], h)
                log.info("%s/%s: %g s horizon: %d windows from %d sequence(s), %d shorter than it",
                         terrain, split, h, n_win, n_seq, short)  # fmt: skip
            data.tests[terrain][split] = seqs
        data.files_of[terrain] = train_files + [s.path for sp in splits for s in data.tests[terrain][sp]]
        data.skipped += protocol_unavailable(
            cal, layout, protocol, terrain, train_files, data.tests[terrain], data.inputs_of
        )
    data.terrains = [t for t in terrains if t in data.inputs_of and data.tests[t]]
    return data
