"""``skidbench split`` and ``skidbench card``.

split: for every ``train``/``cv``/``ld`` sequence of the manifest, ``groundtruth/<seq>.tum`` + the
extracted commands (``cmd_vel`` Twist, or ``cmd_wheels``) and wheel measurements (``joint_states``: the
mean of ``robot.left_joints``/``right_joints`` velocities, or ``enc_wheels``) -> one split file (see
:mod:`.build` for the clock, the hold and the differentiator), then ``splits/card.md``. A ground truth
flagged by the loop-closure check is refused unless ``split.allow_flagged=true``, and so is a sequence
flagged by the ground-truth consistency gate (:mod:`..groundtruth.consistency`: its ground truth's body
velocities against its wheels'); every sequence's gate numbers are in its split file's metadata
(``consistency``) and in the card, with the segments a source left out (``extracted/segments.json``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from skidbench.pipeline.cli.main import stage
from skidbench.pipeline.core.cache import Stamp, stamp_file
from skidbench.pipeline.core.errors import SplitError
from skidbench.pipeline.core.io import fingerprint_file, read_parquet_metadata, write_text_atomic
from skidbench.pipeline.core.layout import Layout, layout_from_cfg, prune_stale
from skidbench.pipeline.core.manifest import SPLITS, Manifest, Sequence
from skidbench.pipeline.core.robot import Robot, robot_from_hydra
from skidbench.pipeline.core.schema import write_split
from skidbench.pipeline.groundtruth.consistency import consistency, describe
from skidbench.pipeline.groundtruth.trajectory import read_tum
from skidbench.pipeline.runner.tasks import map_items
from skidbench.pipeline.splits.build import build_split_table
from skidbench.pipeline.splits.card import dataset_card
from skidbench.pipeline.splits.settings import CardSettings, SplitSettings

log = logging.getLogger("skidbench.split")


def check_flag(layout: Layout, allow: bool) -> None:
    path = layout.groundtruth / "loop_closure.json"
    if not path.is_file():
        raise SplitError(f"{path}: no ground truth report; run `skidbench groundtruth` first")
    report = json.loads(path.read_text())
    if report.get("flagged") and not allow:
        stats = ", ".join(f"{k} {report[k]:.4f}" for k in report if k.endswith("_mean"))
        raise SplitError(
            f"{path}: ground truth flagged by the loop-closure check ({stats}; "
            f"bounds {report.get('bounds')}); "
            "set split.allow_flagged=true to use it anyway"
        )
    if report.get("flagged"):
        log.warning("using a flagged ground truth (split.allow_flagged=true)")


def joint_rates(df: pd.DataFrame, robot: Robot, where: str) -> np.ndarray:
    """(N, 2) (wl, wr): the mean velocity of the robot's left and right joints in each JointState row."""
    names = df["name"].iloc[0]
    lens = df["velocity"].map(len).to_numpy()
    same = (lens == len(names)).all() and df["name"].map(lambda n: list(n) == list(names)).all()
    if not same:
        raise SplitError(f"{where}: joint names or counts change between messages")
    vel = np.stack(df["velocity"].to_numpy()).astype(float)
    idx = {n: i for i, n in enumerate(names)}
    missing = [j for j in (*robot.left_joints, *robot.right_joints) if j not in idx]
    if missing:
        raise SplitError(
            f"{where}: joints {missing} not found (joints: {list(names)}); set robot.left_joints/right_joints"
        )
    left = vel[:, [idx[j] for j in robot.left_joints]].mean(axis=1)
    right = vel[:, [idx[j] for j in robot.right_joints]].mean(axis=1)
    return np.column_stack([left, right])


def _source(path: Path) -> dict[str, str]:
    """A split's record of one file it was made from."""
    return {"path": str(path), "fingerprint": fingerprint_file(path)}


def read_commands(ext: Path) -> tuple[Path, str, np.ndarray, np.ndarray]:
    """(file, kind, bag times in ns, (N, 2) values) of a sequence's extracted commands, in time order:
    ``cmd_vel`` (kind ``twist``: linear_x, angular_z) or else ``cmd_wheels`` (kind ``wheels``: wl, wr)."""
    if (ext / "cmd_vel.parquet").is_file():
        cmd_path, kind, cols = ext / "cmd_vel.parquet", "twist", ["linear_x", "angular_z"]
    elif (ext / "cmd_wheels.parquet").is_file():
        cmd_path, kind, cols = ext / "cmd_wheels.parquet", "wheels", ["wl", "wr"]
    else:
        raise SplitError(
            f"{ext}: no commands (neither cmd_vel nor cmd_wheels was extracted; an extraction made before "
            "extract refused a dataset without them); run `skidbench extract` with source.topics.cmd_vel "
            "naming the topic the robot obeyed"
        )
    c = pd.read_parquet(cmd_path, columns=["bag_time_ns", *cols])
    cmd = c[cols].to_numpy(float)
    if len(c) == 0:
        raise SplitError(f"{cmd_path}: empty sequence (no commands)")
    cmd_t = c["bag_time_ns"].to_numpy(np.int64)
    order = np.argsort(cmd_t, kind="stable")
    return cmd_path, kind, cmd_t[order], cmd[order]


def read_encoders(ext: Path, robot: Robot) -> tuple[np.ndarray | None, np.ndarray | None, Path | None]:
    """(bag times in ns, (N, 2) wheel rates wl/wr, file) of a sequence's wheel measurements: the robot's
    joints of ``joint_states`` (:func:`joint_rates`) or else ``enc_wheels``; (None, None, None) without
    either (or with an empty ``joint_states``)."""
    p = ext / "joint_states.parquet"
    if p.is_file():
        j = pd.read_parquet(p, columns=["bag_time_ns", "name", "velocity"])
        if not len(j):
            return None, None, None
        return j["bag_time_ns"].to_numpy(np.int64), joint_rates(j, robot, str(p)), p
    p = ext / "enc_wheels.parquet"
    if p.is_file():
        j = pd.read_parquet(p, columns=["bag_time_ns", "wl", "wr"])
        return j["bag_time_ns"].to_numpy(np.int64), j[["wl", "wr"]].to_numpy(float), p
    return None, None, None


def apply_gate(df: pd.DataFrame, gate: dict, sp: SplitSettings, layout: Layout, seq: Sequence) -> bool:
    """What the consistency gate's verdict does to a sequence: nothing when not flagged; with
    ``split.drop_flagged`` (and not ``allow_flagged``) every row of ``df`` becomes invalid (in place);
    refused otherwise unless ``allow_flagged`` (returns False, and an earlier run's split file is removed)."""
    if not gate["flagged"]:
        return True
    log.warning("ground truth consistency gate FLAGGED %s", describe(seq.name, gate))
    if sp.drop_flagged and not sp.allow_flagged:
        gate["dropped"] = True  # kept in the manifest's layout, but no row of it is scored or fitted
        df["valid"] = False
        log.warning("%s: dropped (split.drop_flagged=true): every row valid=false", seq.name)
    elif not sp.allow_flagged:
        stale = layout.split_file(seq.terrain, seq.category, seq.name)
        stale.unlink(missing_ok=True)  # an earlier allowed run's file must not be scored now
        return False
    return True


def split_meta(
    df: pd.DataFrame, gate: dict, sp: SplitSettings, robot: Robot, seq: Sequence, sources: dict
) -> dict[str, Any]:
    """The metadata a split file records beside its table."""
    return {
        "consistency": gate,
        "sequence": seq.name,
        "terrain": seq.terrain,
        "split": seq.category,
        "robot": robot.to_dict(),
        "sources": sources,
        "rate_hz": sp.rate_hz,
        "cmd_timeout_s": sp.cmd_timeout,
        "differentiator": {
            "kind": "savitzky_golay",
            "window": sp.differentiator.window,
            "order": sp.differentiator.order,
        },
        "max_wheel_rate": robot.max_wheel_rate,
        "clipped_rows": df.attrs.get("clipped_rows", 0),
        "cmd_association": df.attrs.get("cmd_association"),
    }


def split_sequence(
    sp: SplitSettings, layout: Layout, robot: Robot, seq: Sequence
) -> tuple[Path | None, dict]:
    """Build one sequence's split table and gate it (:func:`consistency`); write it unless the gate
    flags it and ``split.allow_flagged`` is false. Returns (its path or None when refused, the gate's
    numbers)."""
    ext = layout.extracted / seq.name
    tum = layout.groundtruth / f"{seq.name}.tum"
    if not tum.is_file():
        raise SplitError(f"{tum}: no ground truth for {seq.name}; run `skidbench groundtruth`")
    gt = read_tum(tum)
    cmd_path, kind, cmd_t, cmd = read_commands(ext)
    enc_t, enc, enc_path = read_encoders(ext, robot)
    sources = {"groundtruth": _source(tum), "cmd": _source(cmd_path)}
    if enc_path is not None:
        sources["enc"] = _source(enc_path)
    df = build_split_table(
        robot, gt.stamp_ns, gt.se2, gt.gaps, cmd_t, cmd, kind, enc_t, enc, sp.rate_hz,
        sp.cmd_timeout, sp.max_gap, sp.differentiator.window, sp.differentiator.order,
    )  # fmt: skip
    if len(df) == 0 or not df["valid"].any():  # (checked before the gate, which may drop every row)
        raise SplitError(
            f"{tum}: empty sequence: no valid ground truth overlapping the commands of {cmd_path}"
        )
    gate = consistency(df, robot.wheel_radius, robot.track_width, sp.consistency)
    if not apply_gate(df, gate, sp, layout, seq):
        return None, gate
    path = layout.split_file(seq.terrain, seq.category, seq.name)
    meta = split_meta(df, gate, sp, robot, seq, sources)
    write_split(df, path, meta)
    log.info("%s -> %s (%d rows, %.0f%% valid)", seq.name, path, len(df), 100 * df["valid"].mean())
    if meta["clipped_rows"]:
        log.info(
            "%s: wheel commands clipped to +-%g rad/s (robot.max_wheel_rate) in %d of %d rows",
            seq.name, robot.max_wheel_rate, meta["clipped_rows"], len(df),
        )  # fmt: skip
    return path, gate


def run(cfg: DictConfig) -> list[Path]:
    layout = layout_from_cfg(cfg)
    sp: SplitSettings = OmegaConf.to_object(cfg.split)
    check_flag(layout, sp.allow_flagged)
    manifest = Manifest.read(layout.manifest)
    robot = robot_from_hydra(cfg.robot)
    seqs = [s for s in manifest.sequences if s.category in SPLITS]
    if not seqs:
        raise SplitError(f"{layout.manifest}: empty split: no train/cv/ld sequences")
    conf = {
        "split": dataclasses.asdict(sp),
        "robot": OmegaConf.to_container(cfg.robot, resolve=True),
        "metadata": ["cmd_association"],  # what a split file records beyond its table: older ones re-split
    }
    # the sequences are independent: tasks (pipeline/tasks.py: forked workers, or Ray tasks on a cluster)
    calls = [(sp, layout, robot, s, conf) for s in seqs]
    results = map_items(_split_task, calls, [s.name for s in seqs], what="split", unit="seq")
    written = [path for path, _, _ in results if path is not None]
    skipped = sum(fresh for _, _, fresh in results)
    refused = [describe(s.name, gate) for s, (p, gate, _) in zip(seqs, results, strict=True) if p is None]
    if refused:
        raise SplitError(
            f"{layout.splits}: {len(refused)} of {len(seqs)} sequence(s) flagged by the ground-truth "
            f"consistency gate: {refused[0]}"
            + (f" (and {len(refused) - 1} more; the log lists them)" if len(refused) > 1 else "")
            + "; set split.drop_flagged=true to leave them out, or split.allow_flagged=true to use them"
        )
    prune_stale(layout, manifest)  # sequences no longer in the manifest, and the folders left empty
    card_stamp = Stamp(stamp_file(layout.root, "split", "_card.json"), "card")
    segments = [p for p in [layout.extracted / "segments.json"] if p.is_file()]  # the card lists them too
    card_key = card_stamp.key(written + segments, {"robot": conf["robot"], "card": _card_conf(cfg)})
    if not card_stamp.is_fresh(card_key):
        write_card(cfg, layout, robot)
        card_stamp.record(card_key, [layout.splits / "card.md"])
    if skipped == len(seqs):
        log.info("split: %d sequences up to date, skipped", len(seqs))
    elif skipped:
        log.info("split: %d sequences split, %d up to date", len(seqs) - skipped, skipped)
    return written


def _split_task(sp: SplitSettings, layout: Layout, robot: Robot, seq: Sequence, conf: dict):
    """Bring one sequence's split file up to date, in whatever process runs it: skipped when its stamp is
    fresh, else split (:func:`split_sequence`) and stamped. Returns ``(path or None when the gate refused
    it, the gate's numbers when computed, whether it was up to date)``."""
    path = layout.split_file(seq.terrain, seq.category, seq.name)
    stamp = Stamp(stamp_file(layout.root, "split", f"{seq.name}.json"), "split")
    key = stamp.key(split_inputs(layout, seq), {**conf, "terrain": seq.terrain, "category": seq.category})
    if stamp.is_fresh(key):
        return path, None, True
    path, gate = split_sequence(sp, layout, robot, seq)
    if path is not None:
        stamp.record(key, [path])
    return path, gate, False


SPLIT_INPUTS = ("cmd_vel", "cmd_wheels", "joint_states", "enc_wheels")


def split_inputs(layout: Layout, seq: Sequence) -> list[Path]:
    """The files one sequence's split reads (its stamp's inputs)."""
    ext = layout.extracted / seq.name
    files = [layout.groundtruth / f"{seq.name}.tum", *(ext / f"{k}.parquet" for k in SPLIT_INPUTS)]
    return [f for f in files if f.is_file()]


def _card_conf(cfg: DictConfig) -> Any:
    card_cfg: Any = cfg.get("card") or {}
    return OmegaConf.to_container(card_cfg, resolve=True) if OmegaConf.is_config(card_cfg) else card_cfg


def write_card(cfg: DictConfig, layout: Layout, robot: Robot) -> str:
    """The dataset card (``<ds>/splits/card.md``) with the ``card`` section's settings
    (:class:`~skidbench.pipeline.splits.settings.CardSettings`; its defaults for a stage without one)."""
    node = cfg.get("card")
    card = OmegaConf.to_object(node) if node is not None else CardSettings()
    files = [p for p in layout.split_files(Manifest.read(layout.manifest)) if p.is_file()]
    text = dataset_card(layout.splits, robot, card.paper, files)
    text += gate_section(files) + recording_section(layout) + segments_section(layout)
    write_text_atomic(layout.splits / "card.md", text)
    return text


def gate_section(files: list[Path]) -> str:
    """Markdown: each split file's ground-truth consistency numbers (its metadata's ``consistency``)."""
    rows = []
    for p in files:
        rep = read_parquet_metadata(p).get("consistency")
        if not rep:
            continue

        def f(v, fmt):
            return "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, fmt)

        rows.append(
            f"| {p.stem} | {rep.get('wheels')} | {f(rep.get('sign_agreement'), '.2f')} | "
            f"{f(_plus0(rep.get('heading_offset_deg')), '.0f')} | {f(rep.get('corr_v'), '.2f')} | "
            f"{f(rep.get('corr_w'), '.2f')} | {f(rep.get('uncommanded_s'), '.1f')} | "
            f"{_verdict(rep)} |"
        )
    if not rows:
        return ""
    head = [
        "",
        "## Ground-truth consistency (pipeline/groundtruth/consistency.py)",
        "",
        "| sequence | wheels | sign agreement | heading offset (deg) | corr v | corr w | uncommanded (s) "
        "| gate |",
        "|---|---|---:|---:|---:|---:|---:|---|",
    ]
    return "\n".join(head + rows) + "\n"


MOVED = "moving, not driven by the recorded commands"


def _metres(segs: list[dict]) -> str:
    """Ground-truth path length of segments ("-" when the source has no absolute pose for them)."""
    vals = [s["metres"] for s in segs if s.get("metres") is not None]
    return f"{sum(vals):.1f}" if vals else "-"


def recording_section(layout: Layout) -> str:
    """Markdown: per source file, what extract measured of the recording against the robot (``robot_checks``
    in ``extracted/segments.json``: the wheel-rate peak, the ground truth's metres per wheel radian over
    the spec radius, the measured/commanded speed gain) and the command kinematics identified from it."""
    path = layout.extracted / "segments.json"
    data = json.loads(path.read_text()) if path.is_file() else {}
    rows = [(name, rec) for name, rec in data.items() if rec.get("robot_checks")]
    if not rows:
        return ""
    fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
    out = ["", "## The recording against the robot (measured by extract)", ""]
    out += ["| file | version | robot | wheel peak rad/s | m per wheel rad / spec radius | speed gain | "
            "command kinematics [r, B] |", "|---|---|---|---:|---:|---:|---|"]  # fmt: skip
    for name, rec in rows:
        c = rec["robot_checks"]
        kin = c.get("cmd_kinematics") or {}
        said = f"{kin['value']}: {kin.get('how', '')}" if kin.get("value") else "- (body commands)"
        if kin.get("configured") and kin.get("value") and kin["configured"] != kin["value"]:
            said += f"; the configured fallback {kin['configured']} not used"
        out.append(
            f"| {name} | {rec.get('version', '-')} | {c.get('robot', '-')} | "
            f"{fmt(c.get('max_wheel_rate_measured'), '.2f')} | {fmt(c.get('implied_radius_ratio'), '.2f')} | "
            f"{fmt(c.get('speed_gain'), '.2f')} | {said} |"
        )
    return "\n".join(out) + "\n"


def segments_section(layout: Layout) -> str:
    """Markdown: per source file, the segments left out of Train/CV/LD (``extracted/segments.json``,
    written by sources that classify their rows: seconds, metres, why) and the seconds kept."""
    path = layout.extracted / "segments.json"
    if not path.is_file():
        return ""
    data = json.loads(path.read_text())
    out = ["", "## Segments not driven by the recorded commands (left out unless marked kept)", ""]
    out += [
        "| file | terrain | class | segments | seconds | metres | why |",
        "|---|---|---|---:|---:|---:|---|",
    ]
    for name, rec in data.items():
        segs = rec.get("segments", [])
        kept = [s for s in segs if s["class"] == "command"]
        groups: dict[tuple[str, str], list[dict]] = {}
        for s in segs:
            if s["class"] != "command":
                key = (s["class"] + ("" if s.get("excluded", True) else " (kept)"), s["why"].split(":")[0])
                groups.setdefault(key, []).append(s)
        for (cls, why), g in groups.items():
            out.append(
                f"| {name} | {rec.get('terrain')} | {cls} | {len(g)} | {sum(s['seconds'] for s in g):.1f} | "
                f"{_metres(g)} | {why}: {MOVED if cls.startswith('other') else 'not moving'} |"
            )
        out.append(
            f"| {name} | {rec.get('terrain')} | kept (command-driven) | {len(kept)} | "
            f"{sum(s['seconds'] for s in kept):.1f} | {_metres(kept)} | scored |"
        )
    return "\n".join(out) + "\n"


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="split")
@stage("split")
def main(cfg: DictConfig) -> None:
    run(cfg)


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="card")
@stage("card")
def card_main(cfg: DictConfig) -> None:
    layout = layout_from_cfg(cfg)
    print(write_card(cfg, layout, robot_from_hydra(cfg.robot)))


def _plus0(v):
    """-0.4 prints as "-0" with .0f: add 0.0 after rounding so a zero offset reads "0"."""
    return None if v is None else round(float(v)) + 0.0


def _verdict(rep: dict) -> str:
    if not rep.get("flagged"):
        return "ok"
    return ("DROPPED" if rep.get("dropped") else "FLAGGED (used)") + ": " + "; ".join(rep.get("reasons", []))
