"""Stereo visual odometry with OpenCV: the ``vo`` ground-truth method.

The algorithm (ORB keyframes, stereo matching refined by Lucas-Kanade, PnP with RANSAC and a robust
stereo refinement, keyframe policy, tracking-loss gaps) is described in :mod:`.stereo_vo`.

Three modules: the algorithm on arrays (:mod:`.stereo_vo`: :class:`StereoVO`, :class:`VOConfig`); a bag's
stereo pairs (:mod:`.stereo_bag`: camera_info, topics, left/right pairing by header stamp, decoding); and
this one, the method's entry point: :func:`run_stereo_vo` takes what it reads of the stage config as a
:class:`StereoSettings` (``robot.camera``, ``groundtruth.vo``, ``source.topics``,
``extract.typestores``; the app reads them once), streams the bag's pairs through the
algorithm and returns the base-frame trajectory ``T_b0_bi = T_b_c T_c0_ci T_b_c^-1``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from skidbench.pipeline.core.errors import GroundTruthError, SkidbenchError, one_line
from skidbench.pipeline.groundtruth.stereo.stereo_bag import (
    check_image_topics,
    iter_stereo_frames,
    open_stereo_bag,
    read_stereo_camera,
)
from skidbench.pipeline.groundtruth.stereo.stereo_vo import StereoVO
from skidbench.pipeline.groundtruth.stereo.vo_settings import (
    VOConfig,
    camera_extrinsic,
)
from skidbench.pipeline.groundtruth.trajectory import Trajectory

__all__ = ["run_stereo_vo", "StereoSettings", "source_image_topics", "extracted_image_topics"]


def _get(node: Any, path: str, default: Any = None) -> Any:
    cur = node
    for part in path.split("."):
        try:
            cur = cur[part]
        except (KeyError, TypeError, AttributeError):
            return default
        if cur is None:
            return default
    return cur


@dataclass(frozen=True)
class StereoSettings:
    """What the ``vo`` method reads of the stage config: the left camera's pose on the robot
    (``robot.camera``: ``xyz``, ``rpy``), the VO options (``groundtruth.vo``), the stereo topics as
    ``source.topics`` names them (a mapping, or ``auto``: those extract chose) and the default typestore
    per bag format (``extract.typestores``; None: DEFAULT_STORES)."""

    camera: Mapping[str, Any] | None = None
    options: Mapping[str, Any] = field(default_factory=dict)
    topics: Any = None
    typestores: Mapping[str, str] | None = None


def _vo_config(
    settings: StereoSettings, vo: VOConfig | Mapping[str, Any] | None, extracted: str | Path | None = None
) -> VOConfig:
    if isinstance(vo, VOConfig):
        return vo
    options = dict(settings.options if vo is None else vo)
    return VOConfig.from_mapping({**source_image_topics(settings.topics, extracted), **options})


# VOConfig option <- the extraction's topic key: VO reads the topics extract was configured with
_SOURCE_TOPICS = {
    "left_topic": "left_image",
    "right_topic": "right_image",
    "left_info_topic": "left_info",
    "right_info_topic": "right_info",
}


def source_image_topics(topics: Any, extracted: str | Path | None = None) -> dict[str, str]:
    """``source.topics`` (``topics``) ``{left,right}_{image,info}.topic`` as VO options (``left_topic``
    ...): a bag whose stereo pair is on other topics (raw ``image_raw`` included) is set once, for extract
    and VO alike; ``groundtruth.vo.*`` still overrides. With ``source.topics=auto`` the topics are those
    extract chose for this bag, read from ``extracted`` (the sequence's folder, its ``_extract.json``)."""
    if topics == "auto":
        return extracted_image_topics(extracted) if extracted is not None else {}
    out = {}
    for option, key in _SOURCE_TOPICS.items():
        topic = _get(topics, f"{key}.topic")
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
    settings: StereoSettings,
    vo: VOConfig | Mapping[str, Any] | None = None,
    stats: dict | None = None,
    extracted: str | Path | None = None,
) -> Trajectory:
    """Stereo VO over a bag's images -> base-frame trajectory (first pose = identity), header stamps.

    ``settings``: the camera extrinsic, the VO options (``vo``, when given, replaces them), the stereo
    topics and the typestores (built by the app from its config). ``stats``, if given, receives the run's
    counters (frames, keyframes, lost frames, frames/s). ``extracted``: the sequence's extracted folder,
    whose ``_extract.json`` names the stereo topics when ``source.topics=auto``. Every bag problem is one
    GroundTruthError.
    """
    bag_path = Path(bag_path)
    vocfg = _vo_config(settings, vo, extracted)
    camera_cfg = settings.camera
    try:
        with open_stereo_bag(bag_path, settings.typestores) as reader:
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
