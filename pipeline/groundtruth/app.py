"""``skidbench groundtruth``: every sequence of the manifest -> ``groundtruth/<seq>.tum`` + ``<seq>.json``,
then the loop-closure check over the ``loop`` sequences -> ``groundtruth/loop_closure.json``.

``groundtruth.method``: ``vo`` (stereo VO from the bag, :mod:`.vo`), ``orbslam`` (ORB-SLAM files from
``groundtruth.orbslam.dir``, :mod:`.orbslam`) or ``pose_topic`` (an extracted pose table, :mod:`.pose_topic`).
When the simulator's truth table is present the ground truth is also scored against it (absolute and
``relative_horizon`` s relative error), per sequence and over the dataset.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from skidbench.pipeline.cli.main import stage
from skidbench.pipeline.core.cache import Stamp, stamp_file
from skidbench.pipeline.core.errors import ConfigError, GroundTruthError
from skidbench.pipeline.core.geometry import se3_from_xyz_rpy
from skidbench.pipeline.core.io import fingerprint_file, write_json_atomic, write_text_atomic
from skidbench.pipeline.core.layout import Layout, layout_from_cfg
from skidbench.pipeline.core.manifest import Manifest, Sequence
from skidbench.pipeline.groundtruth.orbslam import read_orbslam
from skidbench.pipeline.groundtruth.pose_topic import read_pose_table
from skidbench.pipeline.groundtruth.settings import GroundTruthSettings, OrbslamSettings, PoseTopicSettings
from skidbench.pipeline.groundtruth.tf import is_tf_table, read_tf_trajectory
from skidbench.pipeline.groundtruth.trajectory import Trajectory, read_tum, write_tum
from skidbench.pipeline.runner.cpu import code_paths
from skidbench.pipeline.runner.tasks import map_items

log = logging.getLogger("skidbench.groundtruth")

LOOP_REPORT = "loop_closure.json"


@dataclass(frozen=True)
class GroundTruthConfig:
    """What the stage reads of its config, read once (:meth:`from_cfg`): the ``groundtruth`` section, the
    robot (its camera; the stamps' config), the stereo topics as ``source.topics`` names them and the
    typestore per bag format (``extract.typestores``, when the config has it: VO reads the bag)."""

    gt: GroundTruthSettings
    robot: dict[str, Any]
    topics: Any = None
    typestores: dict[str, str] | None = None

    @classmethod
    def from_cfg(cls, cfg: DictConfig) -> GroundTruthConfig:
        def plain(node: Any) -> Any:
            return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node

        extract = cfg.get("extract")
        return cls(
            gt=OmegaConf.to_object(cfg.groundtruth),
            robot=plain(cfg.robot),
            topics=plain(cfg.source.get("topics")) if cfg.get("source") is not None else None,
            typestores=plain(extract.get("typestores")) if extract is not None else None,
        )


def camera_extrinsic(robot: dict[str, Any]) -> np.ndarray:
    """``T_b_c`` from ``robot.camera`` (xyz + rpy); ConfigError naming the settings to add when the robot's
    config has no camera (or only part of its pose): ``+robot.camera...`` adds what a robot config lacks."""
    cam = robot.get("camera") or {}
    missing = [k for k in ("xyz", "rpy") if cam.get(k) is None]
    if missing:
        add = " ".join(f"+robot.camera.{k}=[{'x,y,z' if k == 'xyz' else 'roll,pitch,yaw'}]" for k in missing)
        absent = " and ".join(f"robot.camera.{k}" for k in missing)
        raise ConfigError(
            f"robot={robot.get('name')}: no camera extrinsic ({absent} absent); add it: {add} (the camera in "
            "the base frame, m and rad; '+' adds a setting the robot's config does not have)"
        )
    return se3_from_xyz_rpy(np.array(cam["xyz"], dtype=float), np.array(cam["rpy"], dtype=float))


def _extracted_bytes(layout: Layout, seq: Sequence) -> int:
    """Bytes of a sequence's extracted tables: the proxy for how long its ground truth takes."""
    folder = layout.extracted / seq.name
    return sum(p.stat().st_size for p in folder.glob("*") if p.is_file()) if folder.is_dir() else 0


def _sequence_task(
    cfg: GroundTruthConfig, layout: Layout, manifest: Manifest, seq: Sequence, threads: int | None
):
    """Bring one sequence's ground truth up to date, in whatever process runs it (a forked worker, a Ray
    task): skipped when its stamp is fresh, else computed (:func:`sequence_groundtruth`), written and
    stamped here. Returns only its summary: ``(name, skipped, truth error or None, loop error or None)``
    (the loop error of a ``loop`` sequence, for the loop-closure check). ``threads`` limits OpenCV's
    thread pool (one per worker when the workers already fill the cores: its idle threads otherwise spin
    and take CPU time from the other worker; the workers' BLAS is limited by their runner)."""
    out = layout.groundtruth
    tum, rep = out / f"{seq.name}.tum", out / f"{seq.name}.json"
    stamp = Stamp(stamp_file(layout.root, "groundtruth", f"{seq.name}.json"), "groundtruth")
    key = stamp.key(sequence_inputs(cfg.gt, layout, manifest, seq), stage_config(cfg))
    if stamp.is_fresh(key):
        report = json.loads(rep.read_text())
        loop = _loop_error(read_tum(tum), seq) if seq.category == "loop" else None
        return seq.name, True, report.get("truth_error") or None, loop
    if threads is not None:
        import cv2

        cv2.setNumThreads(threads)
    traj, report = sequence_groundtruth(cfg, layout, manifest, seq)
    report["code_paths"] = code_paths()  # the processor code paths it ran on (pipeline/runner/cpu.py)
    score = _write_sequence(cfg.gt, layout, seq, traj, report)
    stamp.record(key, [tum, rep])
    return seq.name, False, score, _loop_error(traj, seq) if seq.category == "loop" else None


def _loop_error(traj: Trajectory, seq: Sequence):
    """The loop-closure error of one loop trial (:func:`.loop.loop_error`), None without the loop module."""
    try:
        loop = importlib.import_module("skidbench.pipeline.groundtruth.loop")
    except ImportError:
        return None
    return loop.loop_error(traj, seq.name)


def _bag_span(ext: Path) -> tuple[int, int] | None:
    """The bag-clock span (first, last ``bag_time_ns``) of a sequence's extracted tables, or None."""
    lo = hi = None
    for table in sorted(ext.glob("*.parquet")):
        try:
            t = pd.read_parquet(table, columns=["bag_time_ns"])["bag_time_ns"].to_numpy()
        except Exception:  # noqa: BLE001 - a table without bag times (a raw source's) says nothing here
            continue
        if len(t):
            lo = int(t.min()) if lo is None else min(lo, int(t.min()))
            hi = int(t.max()) if hi is None else max(hi, int(t.max()))
    return None if lo is None else (lo, hi)


def _check_overlap(path: Path, traj, ext: Path, seq: str) -> None:
    """GroundTruthError when an ORB-SLAM trajectory's times never overlap the sequence's recording (a
    file of another recording, or times on another clock): its poses would pair with no command."""
    span = _bag_span(ext)
    if span is None or not len(traj):
        return
    t0, t1 = int(traj.stamp_ns[0]), int(traj.stamp_ns[-1])
    if t1 < span[0] or t0 > span[1]:
        raise GroundTruthError(
            f"{path}: poses {t0 * 1e-9:.3f}..{t1 * 1e-9:.3f} s never overlap the recording of {seq} "
            f"({span[0] * 1e-9:.3f}..{span[1] * 1e-9:.3f} s, bag clock); is it this sequence's file? "
            "set groundtruth.orbslam.time_offset (s added to the file's stamps) if its clock differs"
        )


def sequence_groundtruth(cfg: GroundTruthConfig, layout: Layout, manifest: Manifest, seq: Sequence):
    """One sequence's ground truth: ``(Trajectory, report)``; report lists the source files consumed."""
    gt = cfg.gt
    method = gt.method
    ext = layout.extracted / seq.name
    max_gap = gt.max_gap
    if method == "pose_topic":
        path = ext / f"{gt.pose_topic.key}.parquet"
        if not path.is_file():
            raise GroundTruthError(_no_pose_table(path, ext, seq.name))
        pt = gt.pose_topic
        if not gt.allow_wheel_odometry:
            check_independent(path, ext, pt)
        if is_tf_table(path):  # /tf (+ /tf_static): compose parent -> child through the tree
            static = ext / f"{pt.static_key}.parquet" if pt.static_key else None
            paths = [path] + ([static] if static not in (None, path) and static.is_file() else [])
            traj = read_tf_trajectory(paths, pt.parent, pt.child, max_gap, pt.stamp, gt.tf_max_gap)
            frames = {"parent": pt.parent, "child": pt.child}
            return traj, {"files": {str(p): fingerprint_file(p) for p in paths}, "tf": frames}
        traj = read_pose_table(path, max_gap, pt.stamp)
        return traj, {"files": {str(path): fingerprint_file(path)}}
    if method == "orbslam":
        o = gt.orbslam
        if o.dir is None:
            raise ConfigError(
                "groundtruth.method=orbslam: set groundtruth.orbslam.dir=<the folder of the ORB-SLAM files>"
            )
        path = Path(o.dir) / o.pattern.format(seq=seq.name)
        if not path.is_file():
            raise GroundTruthError(_no_orbslam_file(path, o, seq.name))
        times = Path(o.dir) / o.times_pattern.format(seq=seq.name)
        ref_stamp = ref_bag = None
        if o.associate_to:
            ref = ext / f"{o.associate_to}.parquet"
            if ref.is_file():
                tab = pd.read_parquet(ref, columns=["stamp_ns", "bag_time_ns"])
                ref_stamp, ref_bag = tab["stamp_ns"].to_numpy(), tab["bag_time_ns"].to_numpy()
            else:
                log.warning("%s absent: ORB-SLAM stamps + time_offset are taken as bag time", ref)
        traj, report = read_orbslam(
            path, camera_extrinsic(cfg.robot), o.format, o.unit, times if times.is_file() else None,
            o.time_offset, ref_stamp, ref_bag, o.max_diff, max_gap, o.max_speed,
        )  # fmt: skip
        _check_overlap(path, traj, ext, seq.name)
        files = {str(p): fingerprint_file(p) for p in (path, times) if p.is_file()}
        return traj, {**report, "files": files}
    if method == "vo":
        try:
            vo = importlib.import_module("skidbench.pipeline.groundtruth.stereo.vo")
        except ImportError as exc:
            raise GroundTruthError(f"groundtruth.method=vo is not available ({exc}); use pose_topic") from exc
        bag = manifest.resolve(seq)
        stereo = vo.StereoSettings(cfg.robot.get("camera"), gt.vo, cfg.topics, cfg.typestores)
        traj = vo.run_stereo_vo(bag, stereo, extracted=ext)
        fp = fingerprint_file(bag) if bag.is_file() else None
        return traj, {"files": {str(bag): fp}}
    raise ConfigError(f"groundtruth.method={method!r}: expected vo, orbslam or pose_topic")


def sequence_inputs(gt: GroundTruthSettings, layout: Layout, manifest: Manifest, seq: Sequence) -> list[Path]:
    """The files one sequence's ground truth reads (for its stamp): the method's source files, the
    simulator truth table when present, and for ``vo`` the VO code itself."""
    method = gt.method
    ext = layout.extracted / seq.name
    files: list[Path] = []
    if method == "pose_topic":
        files.append(ext / f"{gt.pose_topic.key}.parquet")
        if gt.pose_topic.static_key:  # read with a TF table
            files.append(ext / f"{gt.pose_topic.static_key}.parquet")
    elif method == "orbslam":
        o = gt.orbslam
        d = Path(o.dir or ".")
        files += [d / o.pattern.format(seq=seq.name), d / o.times_pattern.format(seq=seq.name)]
        if o.associate_to:
            files.append(ext / f"{o.associate_to}.parquet")
    elif method == "vo":
        here = Path(__file__).parent
        vo_code = [*sorted((here / "stereo").glob("*.py")), here / "app.py"]  # every module of the method
        files += [manifest.resolve(seq), *vo_code]
        files.append(ext / "_extract.json")  # the stereo topics, when source.topics=auto
    files.append(ext / f"{gt.truth_key}.parquet")
    return [f for f in files if f.exists()]


def stage_config(cfg: GroundTruthConfig) -> dict[str, Any]:
    """The config sections ground truth reads (its stamps' config)."""
    gt = dataclasses.asdict(cfg.gt)
    gt.pop("jobs", None)  # how many processes compute it does not change the result
    out = {"groundtruth": gt, "robot": cfg.robot}
    if cfg.gt.method == "vo":  # VO reads the stereo topics of source.topics
        from skidbench.pipeline.groundtruth.stereo.vo import source_image_topics

        out["vo_topics"] = source_image_topics(cfg.topics)
    return out


def _write_if_changed(path: Path, obj: Any) -> None:
    text = json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n"
    if not path.is_file() or path.read_text() != text:
        write_text_atomic(path, text)


def check_independent(path: Path, ext: Path, pt: PoseTopicSettings) -> None:
    """GroundTruthError when the pose table is wheel odometry (:func:`wheel_odometry`): a pose computed
    from the wheel encoders, the same wheels whose commands and rates drive the models, would score them
    against their own inputs. ``groundtruth.allow_wheel_odometry=true`` takes it anyway."""
    info = json.loads((ext / "_extract.json").read_text()) if (ext / "_extract.json").is_file() else {}
    topic = (info.get("topics") or {}).get(pt.key, {})
    why = wheel_odometry(pt.key, topic.get("topic"), pt.parent if is_tf_table(path) else None)
    if why:
        raise GroundTruthError(
            f"{path}: {why}, not ground truth: the wheel encoders it is computed from are the models' own "
            "inputs, so every model would be scored against them; give an independent pose "
            "(groundtruth.pose_topic.key=<a lidar, motion-capture or GNSS pose table>, or "
            "groundtruth.method=orbslam), or set groundtruth.allow_wheel_odometry=true to use it anyway"
        )


#: odometry topics of lidar, visual and inertial estimators whose names end like a drive controller's
#: (``/dlio/odom_node/odom``, ``/rtabmap/odom``, ``/camera/odom/sample``): not wheel odometry
ESTIMATOR_ODOMETRY = (
    r"lio|loam|kiss|rtabmap|vins|mapping|mapped|laser|scan|camera|zed|t265|realsense|odom_node"
)


def wheel_odometry(key: str, topic: str | None, tf_parent: str | None) -> str | None:
    """Why a pose source is wheel odometry, or None: a TF chain from the ``odom`` frame (REP 105's
    odometry frame, which a skid-steer's drive controller publishes from its encoders), or a topic (else
    the table's key) with one of the names `skidbench inspect` proposes for wheel odometry first (the
    drive controller's odom, ``/odom``, ``wheel_odom``, ``odometry/wheel`` ...; never a name of lidar,
    visual, GNSS or mocap odometry (:data:`ESTIMATOR_ODOMETRY`) or of a filter's output)."""
    import re

    from skidbench.pipeline.extract.inspect import fits_role

    if tf_parent is not None:
        odom = str(tf_parent).strip("/").rsplit("/", 1)[-1] == "odom"
        return (
            f"the TF chain from frame {tf_parent!r} (the odometry frame) is wheel odometry" if odom else None
        )
    name = topic or key
    wheel = fits_role("odom", name, tiers=2) and not re.search(ESTIMATOR_ODOMETRY, name.lower())
    return f"{name} is wheel odometry" if wheel else None


def _no_pose_table(path: Path, ext: Path, seq: str) -> str:
    """Why a sequence has no pose table, in one line: the recording's own reason when extract recorded one
    (``_extract.json`` notes, e.g. DRIVE's ``no ground truth: the ICP pose never changes ...``: led by the
    source file, with the settings that would give a ground truth), else the table's path."""
    info = json.loads((ext / "_extract.json").read_text()) if (ext / "_extract.json").is_file() else {}
    notes = [str(n) for n in info.get("notes", [])]
    gt = [n for n in notes if n.startswith("no ground truth")]
    if gt:
        src = ", ".join(str(k) for k in info.get("sources", {})) or str(ext)
        return (
            f"{src}: nothing to score {seq} against: {'; '.join(gt)}, so extract wrote no {path.name}; give "
            "another ground truth: groundtruth.method=orbslam groundtruth.orbslam.dir=<one trajectory file "
            "per sequence>, or groundtruth.pose_topic.key=<a pose table of the extraction>"
        )
    why = f" ({'; '.join(notes)})" if notes else ""
    return f"{path}: pose table not found{why}; set groundtruth.pose_topic.key or run `skidbench extract`"


def _no_orbslam_file(path: Path, o: OrbslamSettings, seq: str) -> str:
    """Why ``path`` is not there, naming the setting that fixes it: ``groundtruth.orbslam.dir`` when the
    folder does not exist or holds no trajectory file, else ``groundtruth.orbslam.pattern`` (with the
    pattern that names the file there, when one file or one naming with the sequence's name fits)."""
    folder = Path(str(o.dir))
    if not folder.is_dir():
        return f"{folder}: no such folder; set groundtruth.orbslam.dir=<the folder of the ORB-SLAM files>"
    there = sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix in (".txt", ".tum", ".csv"))
    if not there:
        return f"{folder}: holds no ORB-SLAM file (.txt, .tum, .csv); set groundtruth.orbslam.dir"
    named = [n.replace(seq, "{seq}") for n in there if seq in n and "times" not in n]
    fits = named if len(named) == 1 else [n for n in there if "times" not in n]
    hint = f"groundtruth.orbslam.pattern='{fits[0]}'" if len(fits) == 1 else "groundtruth.orbslam.pattern"
    shown = ", ".join(there[:6]) + (" ..." if len(there) > 6 else "")
    return (
        f"{path}: no ORB-SLAM file for sequence {seq} (groundtruth.orbslam.pattern={o.pattern!r} in "
        f"{folder}, which holds {shown}); set {hint} ({{seq}} stands for the sequence's name)"
    )


def truth_errors(gt: Trajectory, truth: Trajectory, horizon_s: float) -> dict[str, float] | None:
    """The ground truth against the simulator's truth (:func:`.loop.evaluate_against_truth`: start-pose
    aligned absolute error and ``horizon_s`` relative error); None when they do not overlap in time."""
    from skidbench.pipeline.groundtruth.loop import evaluate_against_truth

    try:
        return evaluate_against_truth(gt, truth, rpe_window_s=horizon_s)
    except GroundTruthError:
        return None


def loop_closure(gt: GroundTruthSettings, errors: dict[str, Any]) -> dict[str, Any]:
    """The loop-closure check (the paper's localization accuracy) with :mod:`.loop`'s formulas, from each
    loop trial's :class:`.loop.LoopError` (None where the loop module is not available)."""
    bounds = dataclasses.asdict(gt.loop_bound)
    if not errors:
        return {"trials": 0, "flagged": False, "bounds": bounds, "note": "no loop sequences in the manifest"}
    try:
        loop = importlib.import_module("skidbench.pipeline.groundtruth.loop")
    except ImportError as exc:
        log.warning("loop-closure module unavailable (%s): check skipped", exc)
        return {"trials": len(errors), "flagged": False, "bounds": bounds, "note": f"check skipped: {exc}"}
    stats = loop.summarize_loops(list(errors.values()), bounds["translational"], bounds["rotational"])
    return {
        "trials": len(errors),
        "sequences": list(errors),
        "translational_mean": stats["trans_err_mean"],
        "translational_std": stats["trans_err_std"],
        "rotational_mean": stats["rot_err_mean"],
        "rotational_std": stats["rot_err_std"],
        "paper": {"translational_mean": 0.004, "translational_std": 0.003,
                  "rotational_mean": 0.002, "rotational_std": 0.002},
        "per_trial": stats["trials"],
        "reasons": stats["reasons"],
        "bounds": bounds,
        "flagged": stats["flagged"],
    }  # fmt: skip


def _write_sequence(
    gt_cfg: GroundTruthSettings, layout: Layout, seq: Sequence, traj: Trajectory, report: dict
) -> dict | None:
    """Write one computed sequence's TUM and report (with its error against the recording's own truth
    pose, when it has one that is not the ground truth itself); returns that error (None without)."""
    out = layout.groundtruth
    tum, rep = out / f"{seq.name}.tum", out / f"{seq.name}.json"
    if len(traj) < 2:
        raise GroundTruthError(f"{seq.name}: empty sequence ({len(traj)} pose)")
    truth_path = layout.extracted / seq.name / f"{gt_cfg.truth_key}.parquet"
    is_truth = gt_cfg.method == "pose_topic" and gt_cfg.pose_topic.key == gt_cfg.truth_key
    score = None
    if truth_path.is_file() and not is_truth:
        truth = read_pose_table(truth_path, gt_cfg.max_gap)
        score = truth_errors(traj, truth, gt_cfg.relative_horizon) or None
        if score:
            report["truth_error"] = score
    dur = (traj.stamp_ns[-1] - traj.stamp_ns[0]) * 1e-9
    report.update(
        {"sequence": seq.name, "terrain": seq.terrain, "category": seq.category,
         "method": gt_cfg.method,
         "poses": len(traj), "duration_s": dur, "gaps": [[a, b] for a, b in traj.gaps]}
    )  # fmt: skip
    write_tum(traj, tum, header=f"skidbench groundtruth {seq.name} method={gt_cfg.method}")
    write_json_atomic(rep, report)
    log.info("%s: %d poses, %.1f s, %d gap(s)", seq.name, len(traj), dur, len(traj.gaps))
    return score


def _loop_report(
    gt: GroundTruthSettings, manifest: Manifest, loops: dict, truth_scores: dict
) -> dict[str, Any]:
    """The loop-closure report of the loops, with the mean truth errors, in manifest order (whatever order
    the workers finished in: the dataset means are summed in it)."""
    rank = {seq.name: i for i, seq in enumerate(manifest.sequences)}
    loops = dict(sorted(loops.items(), key=lambda kv: rank[kv[0]]))
    truth_scores = dict(sorted(truth_scores.items(), key=lambda kv: rank[kv[0]]))
    result = loop_closure(gt, loops)
    result["method"] = gt.method
    if truth_scores:
        keys = ("ate_rms_m", "rpe_trans_rms_m", "rpe_trans_rel_rms", "rpe_yaw_rms_rad")
        result["truth_error"] = {
            k: float(np.mean([s[k] for s in truth_scores.values() if s.get(k) is not None]))
            for k in keys
            if any(s.get(k) is not None for s in truth_scores.values())
        }
    return result


def run(cfg: DictConfig) -> dict[str, Any]:
    """Bring every sequence's ground truth up to date and write the loop-closure report; returns it."""
    layout = layout_from_cfg(cfg)
    manifest = Manifest.read(layout.manifest)
    job = GroundTruthConfig.from_cfg(cfg)
    seqs = manifest.sequences
    # Sequences are independent: each is a task (pipeline/tasks.py: forked workers here, or Ray tasks on
    # a cluster) that checks its stamp, computes, writes and stamps its ground truth and returns its
    # scores, longest first (by extracted bytes) so that no worker is left alone with a long one at the
    # end; a stopped run keeps the finished sequences. Stereo VO is CPU-bound and gets a worker per core;
    # reading a pose table or an ORB-SLAM file takes less than starting a worker process: in this one.
    jobs = job.gt.jobs if len(seqs) > 1 and job.gt.method == "vo" else 1
    order = sorted(seqs, key=lambda seq: -_extracted_bytes(layout, seq))
    threads = 1 if jobs > 1 else None
    calls = [(job, layout, manifest, seq, threads) for seq in order]
    names = [seq.name for seq in order]
    results = map_items(_sequence_task, calls, names, what="groundtruth", unit="seq", jobs=jobs)
    skipped = sum(r[1] for r in results)
    truth_scores = {name: score for name, _, score, _ in results if score}
    loops = {name: err for name, _, _, err in results if err is not None}
    result = _loop_report(job.gt, manifest, loops, truth_scores)
    _write_if_changed(layout.groundtruth / LOOP_REPORT, result)
    n = len(seqs)
    if skipped == n:
        log.info("groundtruth: %d sequences up to date, skipped", n)
    elif skipped:
        log.info("groundtruth: %d sequences computed, %d up to date", n - skipped, skipped)
    if result.get("flagged"):
        log.warning(
            "ground truth FLAGGED by the loop-closure check: %s",
            {k: result.get(k) for k in result if k.endswith("_mean")},
        )
    return result


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="groundtruth")
@stage("groundtruth")
def main(cfg: DictConfig) -> None:
    log.debug(OmegaConf.to_yaml(cfg))
    run(cfg)
