"""The ``groundtruth:`` section of the ground-truth stage's config (the keys ``groundtruth.<field>``): which
method gives the poses and how it reads them. The dataclass is the section's schema and defaults (stored in
Hydra's ConfigStore, ``pipeline/cli/config_schema.py``; conf/groundtruth.yaml lists it); the stage reads
it whole, ``OmegaConf.to_object(cfg.groundtruth)``. Imports nothing heavy (the schema is registered before
every composition)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

#: the ground-truth methods: stereo VO from the bag, ORB-SLAM files, an extracted pose table
METHODS = ("vo", "orbslam", "pose_topic")


@dataclass(frozen=True)
class PoseTopicSettings:
    """``groundtruth.pose_topic.*``: the extracted table (``key``: true_pose, gt_pose, odom, mocap..., or
    ``tf``, a tf2_msgs/TFMessage table: the pose of ``child`` in ``parent``, composed through the TF tree
    with the ``static_key`` table's static edges applied once), which clock its stamps are on, and the
    longest hole a TF edge is interpolated across (null: ``groundtruth.max_gap``)."""

    key: str = "${oc.select:source.groundtruth_key,true_pose}"  # a raw source names its pose table
    stamp: str = field(default="bag_time_ns", metadata={"choices": ("bag_time_ns", "stamp_ns")})
    parent: str | None = None  # e.g. map, odom, world (a mocap bridge's frame)
    child: str | None = None  # e.g. base_link, base_footprint
    static_key: str | None = "tf_static"
    tf_max_gap: float | None = field(default=None, metadata={"gt": 0, "what": "s; null: groundtruth.max_gap"})


@dataclass(frozen=True)
class OrbslamSettings:
    """``groundtruth.orbslam.*``: one file per sequence, ``<dir>/<pattern>`` (KITTI: with
    ``<dir>/<times_pattern>``), ``{seq}`` standing for the sequence's name; its format and time unit
    (``auto``: detected; a unit that contradicts the data is an error), the seconds added to its stamps to
    reach the bag clock, the extracted table whose stamps the poses snap to (null: no snapping) within
    ``max_diff``, and the speed above which a jump is a tracking reset (a gap). ``dir`` has no default:
    ``groundtruth.method=orbslam`` needs it."""

    dir: str | None = None
    pattern: str = "{seq}.txt"
    times_pattern: str = "{seq}.times.txt"
    format: str = field(default="auto", metadata={"choices": ("auto", "tum", "euroc", "kitti")})
    unit: str = field(default="auto", metadata={"choices": ("auto", "s", "ns")})
    time_offset: float = field(default=0.0, metadata={"what": "s"})
    associate_to: str | None = "left_image"
    max_diff: float = field(default=0.02, metadata={"gt": 0, "what": "s"})
    max_speed: float = field(default=10.0, metadata={"gt": 0, "what": "m/s"})


@dataclass(frozen=True)
class LoopBound:
    """``groundtruth.loop_bound.*``: a mean relative loop-closure error above these flags the ground
    truth."""

    translational: float = field(default=0.01, metadata={"gt": 0})
    rotational: float = field(default=0.01, metadata={"gt": 0})


@dataclass(frozen=True)
class GroundTruthSettings:
    """``groundtruth.*``: the method (:data:`METHODS`; by default the source's ``groundtruth_method``, else
    ``vo``), how many processes compute stereo VO (a pose table or an ORB-SLAM file is read in one), the
    longest hole between poses that is not a tracking-loss gap, whether wheel odometry may be taken as ground
    truth (it is computed from the encoders the models' inputs come from), each method's options (``vo``:
    options of the stereo VO, added with ``+``, the fields of :class:`~.stereo.vo_settings.VOConfig`; the
    config check names an unknown one before the stage starts), the simulator's truth table (used only to
    score the ground truth), the horizon of the relative error against it, and the loop-closure bounds."""

    method: str = field(default="${oc.select:source.groundtruth_method,vo}", metadata={"choices": METHODS})
    jobs: int = field(default=2, metadata={"lo": 1})
    max_gap: float = field(default=0.5, metadata={"gt": 0, "what": "s"})
    allow_wheel_odometry: bool = False
    pose_topic: PoseTopicSettings = field(default_factory=PoseTopicSettings)
    orbslam: OrbslamSettings = field(default_factory=OrbslamSettings)
    vo: dict[str, Any] = field(default_factory=dict)
    truth_key: str = "true_pose"
    relative_horizon: float = field(default=6.0, metadata={"gt": 0, "what": "s"})
    loop_bound: LoopBound = field(default_factory=LoopBound)

    @property
    def tf_max_gap(self) -> float:
        """The longest hole a TF edge is interpolated across (s)."""
        gap = self.pose_topic.tf_max_gap
        return self.max_gap if gap is None else gap
