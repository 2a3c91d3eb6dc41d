"""Stereo visual odometry with OpenCV: the ``vo`` ground-truth method.

The algorithm (ORB keyframes, stereo matching refined by Lucas-Kanade, PnP with RANSAC and a robust
stereo refinement, keyframe policy, tracking-loss gaps) is described in :mod:`.stereo_vo`.

Three modules: the algorithm on arrays (:mod:`.stereo_vo`: :class:`StereoVO`, :class:`VOConfig`); a bag's
stereo pairs (:mod:`.stereo_bag`: camera_info, topics, left/right pairing by header stamp, decoding); and
this one, the method's entry point: :func:`run_stereo_vo` reads the stage config (``robot.camera``,
``groundtruth.vo``, ``source.topics``, ``extract.typestores``), streams the bag's pairs through the
algorithm and returns the base-frame trajectory ``T_b0_bi = T_b_c T_c0_ci T_b_c^-1``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from ..errors import GroundTruthError, SkidbenchError, one_line
from .orbslam import base_to_camera, camera_to_base
from .stereo_bag import check_image_topics, iter_stereo_frames, open_stereo_bag, read_stereo_camera
from .stereo_vo import StereoCamera, StereoVO, VOConfig, VOStats, camera_extrinsic
from .trajectory import Trajectory

__all__ = [
    "VOConfig",
    "StereoVO",
    "StereoCamera",
    "VOStats",
    "run_stereo_vo",
    "camera_extrinsic",
    "camera_to_base",
    "base_to_camera",
    "read_stereo_camera",
    "iter_stereo_frames",
    "source_image_topics",
    "extracted_image_topics",
]


def _get(cfg: Any, path: str, default: Any = None) -> Any:
    cur = cfg
    for part in path.split("."):
        try:
            cur = cur[part]
        except (KeyError, TypeError, AttributeError):
            return default
        if cur is None:
            return default
    return cur


def _open(bag_path: Path, cfg: Any):
    """The bag open for reading with the config's ``extract.typestores`` (default: DEFAULT_STORES)."""
    return open_stereo_bag(bag_path, _get(cfg, "extract.typestores", None))


def _vo_config(
    cfg: Any, vo: VOConfig | Mapping[str, Any] | None, extracted: str | Path | None = None
) -> VOConfig:
    if isinstance(vo, VOConfig):
        return vo
    if vo is None:
        vo = _get(cfg, "groundtruth.vo", None)
        if vo is not None and not isinstance(vo, Mapping):
            vo = dict(vo)
        if vo is not None and OmegaConf.is_config(vo):
            vo = OmegaConf.to_container(vo, resolve=True)
    return VOConfig.from_mapping({**source_image_topics(cfg, extracted), **dict(vo or {})})


# VOConfig option <- the extraction's topic key: VO reads the topics extract was configured with
_SOURCE_TOPICS = {
    "left_topic": "left_image",
    "right_topic": "right_image",
    "left_info_topic": "left_info",
    "right_info_topic": "right_info",
}


def source_image_topics(cfg: Any, extracted: str | Path | None = None) -> dict[str, str]:
    """``source.topics.{left,right}_{image,info}.topic`` as VO options (``left_topic`` ...): a bag whose
    stereo pair is on other topics (raw ``image_raw`` included) is set once, for extract and VO alike;
    ``groundtruth.vo.*`` still overrides. With ``source.topics=auto`` the topics are those extract chose
    for this bag, read from ``extracted`` (the sequence's folder, its ``_extract.json``)."""
    if _get(cfg, "source.topics") == "auto":
        return extracted_image_topics(extracted) if extracted is not None else {}
    out = {}
    for option, key in _SOURCE_TOPICS.items():
        topic = _get(cfg, f"source.topics.{key}.topic")
        if topic:
            out[option] = str(topic)
    return out


def extracted_image_topics(extracted: str | Path) -> dict[str, str]:
    """The stereo topics ``skidbench extract`` recorded in ``<extracted>/_extract.json``, as VO options."""
    info_path = Path(extracted) / "_extract.json"
    if not info_path.is_file():
        return {}
    topics = json.loads(info_path.read_text()).get("topics", {})
    return {opt: str(topics[key]["topic"]) for opt, key in _SOURCE_TOPICS.items() if key in topics}


def run_stereo_vo(
    bag_path: str | Path,
    cfg: Any,
    vo: VOConfig | Mapping[str, Any] | None = None,
    stats: dict | None = None,
    extracted: str | Path | None = None,
) -> Trajectory:
    """Stereo VO over a bag's images -> base-frame trajectory (first pose = identity), header stamps.

    ``cfg``: the stage config (reads ``robot.camera`` for the extrinsic, ``groundtruth.vo`` for options
    unless ``vo`` is given, ``extract.typestores`` if present). ``stats``, if given, receives the run's
    counters (frames, keyframes, lost frames, frames/s). ``extracted``: the sequence's extracted folder,
    whose ``_extract.json`` names the stereo topics when ``source.topics=auto``. Every bag problem is one
    GroundTruthError.
    """
    bag_path = Path(bag_path)
    vocfg = _vo_config(cfg, vo, extracted)
    camera_cfg = _get(cfg, "robot.camera")
    try:
        with _open(bag_path, cfg) as reader:
            check_image_topics(reader, bag_path, vocfg)  # a bag without images: no ground-truth source
            if camera_cfg is None:
                raise GroundTruthError(
                    f"{bag_path}: robot.camera (the stereo extrinsic) is not configured; set "
                    "robot.camera.xyz and robot.camera.rpy (the left camera's pose in the base frame)"
                )
            T_b_c = camera_extrinsic(camera_cfg)
            camera = read_stereo_camera(reader, bag_path, vocfg)
            engine = StereoVO(camera, vocfg, T_b_c)
            traj = engine.run(iter_stereo_frames(reader, bag_path, vocfg), T_b_c)
    except GroundTruthError:
        raise
    except SkidbenchError as exc:
        raise GroundTruthError(one_line(str(exc))) from exc
    except Exception as exc:  # a damaged bag fails somewhere inside rosbags
        raise GroundTruthError(
            f"{bag_path}: truncated or corrupt bag ({one_line(exc) or type(exc).__name__})"
        ) from exc
    if stats is not None:
        stats.update(engine.stats.as_dict())
    if len(traj) < 2:
        raise GroundTruthError(f"{bag_path}: visual odometry produced {len(traj)} poses")
    return traj
