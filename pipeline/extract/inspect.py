"""``skidbench inspect <path>``: what a bag holds, and which of its topics to extract.

Per topic: message type, count, rate, first/last message and gaps (read streaming, messages not
deserialised). Then a proposed ``source.topics`` mapping, chosen by message type and by the topic
names Clearpath robots (Jackal, Husky, Warthog, Dingo; ROS1 and ROS2 with a namespace) and common
drivers publish, printed as the overrides to paste. ``source.topics=auto`` makes ``extract`` use the same
mapping per bag (:func:`auto_specs`): it logs what it chose and refuses, in one line, when the
required role (``cmd_vel``) is absent or ambiguous.
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
from array import array
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from skidbench.pipeline.core.errors import ExtractError, SkidbenchError, one_line
from skidbench.pipeline.core.layout import register_resolvers
from skidbench.pipeline.extract.convert import normalize_msgtype, schema_for
from skidbench.pipeline.extract.reader import (
    _BAG_ERRORS,
    TopicSpec,
    _bag_error,
    bag_format,
    find_bags,
    open_bag,
)
from skidbench.pipeline.extract.settings import DEFAULT_STORES

log = logging.getLogger("skidbench.extract")

TWIST, TWIST_STAMPED = "geometry_msgs/msg/Twist", "geometry_msgs/msg/TwistStamped"
ODOMETRY, JOINT_STATE, IMU = "nav_msgs/msg/Odometry", "sensor_msgs/msg/JointState", "sensor_msgs/msg/Imu"
POSE_TYPES = (ODOMETRY, "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped")
IMAGE_TYPES = ("sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Image")
CAMERA_INFO, TF_MESSAGE = "sensor_msgs/msg/CameraInfo", "tf2_msgs/msg/TFMessage"
REQUIRED_ROLES = ("cmd_vel",)  # every model reads the commands; the rest is optional
GAP_FACTOR = 5.0  # an interval longer than this many median intervals is a gap

# Ground truth and simulator truth: never wheel odometry or commands.
_TRUTH = r"(ground_?truth|\bgt\b|true_pose|truth|mocap|vicon|optitrack|qualisys|motion_capture)"
# Inputs of a command multiplexer (Clearpath's twist_mux): what someone asked for, not what drove.
_MUX_INPUT = r"(joy_teleop|teleop|twist_marker|interactive|safety|nav_vel|key_?board)"


@dataclass(frozen=True)
class Role:
    """One ``source.topics`` key: the message types it takes and its name tiers (regexes on the topic
    name, best first; a name matching none of them is not proposed)."""

    key: str
    types: tuple[str, ...]
    tiers: tuple[str, ...]
    exclude: str = r"$^"  # names never proposed for this role


ROLES: tuple[Role, ...] = (
    Role(
        "cmd_vel",
        (TWIST, TWIST_STAMPED),
        (
            # what the wheel controller receives (Clearpath ROS1 twist_mux output, ROS2 platform topic)
            r"(velocity_controller|diff_drive_controller|diff_cont|platform)/cmd_vel(_unstamped)?$",
            # the robot's command topic and drivers' equivalents (UT AUTOmata's VESC, Kobuki)
            r"(^|/)(cmd_vel(_unstamped|_out|_stamped)?|vesc_drive|commands/velocity|drive_cmd|cmd_drive)$",
            r"(cmd|vel|drive|twist)",
        ),
        exclude=_TRUTH,
    ),
    Role(
        "odom",
        (ODOMETRY,),
        (
            r"(velocity_controller|diff_drive_controller|diff_cont|platform)/odom$",
            r"(^|/)(odom|wheel_odom|odometry/wheel|wheel/odometry|odom_wheel)$",
            r"odom",
        ),
        exclude=_TRUTH + r"|filtered|ekf|slam|orb|visual|vio|lidar|icp|gps",
    ),
    Role("joint_states", (JOINT_STATE,), (r"(platform/)?joint_states$", r"joint")),
    Role("imu", (IMU,), (r"imu(_0)?/data$|vectornav/imu$", r"imu")),
    Role("true_pose", POSE_TYPES, (_TRUTH,)),
    Role("tf", (TF_MESSAGE,), (r"(^|/)tf$",)),
    Role("tf_static", (TF_MESSAGE,), (r"(^|/)tf_static$",)),
)
STEREO = ("left_image", "right_image", "left_info", "right_info")


@dataclass
class TopicStats:
    """One topic of a bag: ``rate_hz`` from count and span; a gap is an interval over ``GAP_FACTOR``
    median intervals (``max_gap_s`` the longest interval)."""

    topic: str
    msgtype: str
    count: int
    start_ns: int | None = None
    end_ns: int | None = None
    rate_hz: float | None = None
    gaps: int = 0
    max_gap_s: float | None = None


@dataclass
class Proposal:
    """The proposed mapping: ``chosen`` role -> (topic, type); ``ambiguous`` role -> tied topics;
    ``absent`` roles with no candidate."""

    chosen: dict[str, tuple[str, str]] = field(default_factory=dict)
    ambiguous: dict[str, list[str]] = field(default_factory=dict)
    absent: list[str] = field(default_factory=list)


def _supported(msgtype: str) -> bool:
    try:
        schema_for(msgtype)
    except SkidbenchError:
        return False
    return True


def _tier(role: Role, topic: str) -> int | None:
    """0 for the best name tier, 1 for the next ...; None when the name does not fit the role."""
    name = topic.lower()
    if re.search(role.exclude, name):
        return None
    for i, pattern in enumerate(role.tiers):
        if re.search(pattern, name, re.IGNORECASE):
            return i
    return None


def fits_role(key: str, topic: str, tiers: int | None = None) -> bool:
    """Does the name ``topic`` fit the role ``key``: one of its name tiers (of its first ``tiers`` only,
    when given: the specific names, not a catch-all), none of its exclusions?"""
    tier = _tier(next(r for r in ROLES if r.key == key), topic)
    return tier is not None and (tiers is None or tier < tiers)


def propose(topics: Mapping[str, str], counts: Mapping[str, int] | None = None) -> Proposal:
    """The ``source.topics`` mapping for a bag's ``{topic: msgtype}``: per role, the topics of an accepted
    (and extractable) type whose name fits best; mux inputs (teleop, markers) rank below the command the
    robot received. A tie for the best rank is ambiguous. A stereo pair is two image topics whose names
    differ only in left/right, with their camera_info topics."""
    types = {t: normalize_msgtype(m) for t, m in topics.items()}
    out = Proposal()
    for role in ROLES:
        ranked = []
        for topic, msgtype in types.items():
            if msgtype not in role.types or not _supported(msgtype):
                continue
            tier = _tier(role, topic)
            if tier is None:
                continue
            mux = bool(re.search(_MUX_INPUT, topic.lower())) and role.key == "cmd_vel"
            ranked.append(((tier, mux), topic))
        if not ranked:
            out.absent.append(role.key)
            continue
        ranked.sort()
        best = [t for r, t in ranked if r == ranked[0][0]]
        if len(best) > 1:
            out.ambiguous[role.key] = best
        else:
            out.chosen[role.key] = (best[0], types[best[0]])
    _propose_stereo(types, out)
    return out


def _propose_stereo(types: Mapping[str, str], out: Proposal) -> None:
    images = {t for t, m in types.items() if m in IMAGE_TYPES and _supported(m)}
    infos = {t for t, m in types.items() if m == CAMERA_INFO}
    pairs = []
    for left in sorted(images):
        for a, b in (("left", "right"), ("infra1", "infra2"), ("cam0", "cam1")):
            right = left.replace(a, b)
            if a in left and right != left and right in images:
                pairs.append((0 if "rect" in left else 1, "compressed" not in left, left, right))
    if not pairs:
        out.absent.extend(STEREO)
        return
    pairs.sort()
    best = [p for p in pairs if p[:2] == pairs[0][:2]]
    if len(best) > 1:
        out.ambiguous["left_image"] = [p[2] for p in best]
        return
    _, _, left, right = best[0]
    out.chosen["left_image"] = (left, types[left])
    out.chosen["right_image"] = (right, types[right])
    for key, image in (("left_info", left), ("right_info", right)):
        info = _camera_info_of(image, infos)
        if info:
            out.chosen[key] = (info, CAMERA_INFO)
        else:
            out.absent.append(key)


def _camera_info_of(image: str, infos: Iterable[str]) -> str | None:
    """The camera_info of an image topic (``/ns/left/image/compressed``: ``/ns/left/camera_info``)."""
    parts = image.rstrip("/").split("/")
    while len(parts) > 1:
        parts.pop()
        candidate = "/".join(parts) + "/camera_info"
        if candidate in infos:
            return candidate
    return None


def overrides(proposal: Proposal, configured: Iterable[str] = ()) -> list[str]:
    """The ``source.topics.*`` overrides that select the proposal; a configured key the bag lacks
    (``configured``: the keys of the current ``source.topics``) is set to null, except a required role
    (the commands): a dataset without them would fail later, so extract is left to refuse it."""
    lines = []
    for key, (topic, msgtype) in proposal.chosen.items():
        lines += [f"source.topics.{key}.topic={topic}", f"source.topics.{key}.type={msgtype}"]
    lines += [
        f"source.topics.{k}=null" for k in configured if k not in proposal.chosen and k not in REQUIRED_ROLES
    ]
    return lines


# -------------------------------------------------------------------------------------------------
# reading a bag


def inspect_bag(path: Path, stores: Mapping[str, str] = DEFAULT_STORES) -> list[TopicStats]:
    """Per-topic statistics of one bag, by streaming every message once (none deserialised)."""
    path = Path(path)
    with open_bag(path, stores) as reader:
        by_topic: dict[str, list] = {}
        for conn in reader.connections:
            by_topic.setdefault(conn.topic, []).append(conn)
        stamps: dict[str, array] = {t: array("q") for t in by_topic}
        topic_of = {id(c): c.topic for c in reader.connections}
        try:
            for conn, t, _ in reader.messages():
                stamps[topic_of[id(conn)]].append(t)
        except _BAG_ERRORS as exc:
            raise _bag_error(path, exc) from exc
        stats = []
        for topic in sorted(by_topic):
            types = sorted({normalize_msgtype(c.msgtype) for c in by_topic[topic]})
            stats.append(_stats(topic, ", ".join(types), np.frombuffer(stamps[topic], dtype=np.int64)))
    return stats


def _stats(topic: str, msgtype: str, t: np.ndarray) -> TopicStats:
    s = TopicStats(topic, msgtype, int(t.size))
    if t.size:
        s.start_ns, s.end_ns = int(t[0]), int(t[-1])
    if t.size >= 2 and t[-1] > t[0]:
        s.rate_hz = (t.size - 1) / ((t[-1] - t[0]) / 1e9)
        dt = np.diff(t) / 1e9
        s.max_gap_s = float(dt.max())
        s.gaps = int(np.count_nonzero(dt > GAP_FACTOR * np.median(dt)))
    return s


def proposal_for(stats: Iterable[TopicStats]) -> Proposal:
    return propose({s.topic: s.msgtype for s in stats if "," not in s.msgtype})


def auto_specs(bag: Path, stores: Mapping[str, str]) -> list:
    """``source.topics=auto``: the specs of the proposed mapping for ``bag`` (connections only; no
    message is read). Logs the choice; ExtractError (one line) when a required role is absent or
    ambiguous."""
    with open_bag(bag, stores) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
    proposal = propose(topics)
    for key in REQUIRED_ROLES:
        if key in proposal.ambiguous:
            raise ExtractError(
                f"{bag}: source.topics=auto cannot choose {key} among {', '.join(proposal.ambiguous[key])}; "
                f"run `skidbench inspect {bag}` and paste its overrides with the {key} you mean"
            )
        if key not in proposal.chosen:
            listed = ", ".join(f"{t} [{normalize_msgtype(m)}]" for t, m in sorted(topics.items())) or "none"
            raise ExtractError(
                f"{bag}: source.topics=auto found no {key} topic (topics: {listed}); "
                f"set source.topics.{key}.topic and .type"
            )
    for key, tied in proposal.ambiguous.items():
        log.warning("%s: source.topics=auto: %s left out, ambiguous among %s", bag.name, key, ", ".join(tied))
    chosen = ", ".join(f"{k}={t} [{m}]" for k, (t, m) in proposal.chosen.items())
    log.info("%s: source.topics=auto chose %s", bag.name, chosen)
    return [TopicSpec(k, t, m, True) for k, (t, m) in proposal.chosen.items()]


# -------------------------------------------------------------------------------------------------
# the command


def _utc(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


def report(path: Path, stats: list[TopicStats], configured: Iterable[str] = ()) -> str:
    """The text ``skidbench inspect`` prints for one bag."""
    starts = [s.start_ns for s in stats if s.start_ns is not None]
    ends = [s.end_ns for s in stats if s.end_ns is not None]
    total = sum(s.count for s in stats)
    kind = {"ros1": "ROS1 bag", "ros2": f"ROS2 bag ({path.suffix.lstrip('.') or 'folder'})"}[bag_format(path)]
    head = f"{path}: {kind}, {len(stats)} topics, {total} messages"
    if starts:
        t0 = min(starts)
        head += f", {(max(ends) - t0) / 1e9:.1f} s from {_utc(t0)} to {_utc(max(ends))}"
    rows = [("topic", "type", "count", "rate Hz", "start s", "end s", "gaps (longest s)")]
    for s in stats:
        rel = (lambda ns: f"{(ns - t0) / 1e9:.2f}") if starts else str
        rows.append(
            (
                s.topic,
                s.msgtype,
                str(s.count),
                f"{s.rate_hz:.1f}" if s.rate_hz else "-",
                rel(s.start_ns) if s.start_ns is not None else "-",
                rel(s.end_ns) if s.end_ns is not None else "-",
                f"{s.gaps} ({s.max_gap_s:.3f})" if s.max_gap_s is not None else "-",
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = [head, ""]
    lines += ["  " + "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    proposal = proposal_for(stats)
    lines += ["", "proposed source.topics (by message type and topic name):"]
    for key, (topic, msgtype) in proposal.chosen.items():
        lines.append(f"  {key:<12} {topic}  [{msgtype}]")
    for key, tied in proposal.ambiguous.items():
        lines.append(f"  {key:<12} ambiguous: {', '.join(tied)} (choose one)")
    missing = [k for k in proposal.absent if k not in proposal.chosen]
    if missing:
        lines.append(f"  not found: {', '.join(missing)}")
    required = [k for k in REQUIRED_ROLES if k not in proposal.chosen]
    lines += ["", "overrides to paste (or source.topics=auto):"]
    pasted = overrides(proposal, configured)
    chunks = [" ".join(pasted[i : i + 2]) for i in range(0, len(pasted), 2)]
    lines.append("  " + " \\\n  ".join(chunks))
    for key in required:  # what the overrides above cannot give: extract refuses the bag until it is set
        tied = proposal.ambiguous.get(key)
        lines.append(
            f"  {key}: choose one of {', '.join(tied)}: source.topics.{key}.topic=<it> .type=<its type>"
            if tied
            else f"  no {key} topic ({' or '.join(t.rsplit('/', 1)[-1] for t in (TWIST, TWIST_STAMPED))}): "
            f"without commands nothing drives the models, so extract refuses this bag until "
            f"source.topics.{key}.topic and .type name the topic the robot obeyed"
        )
    return "\n".join(lines)


def _configured_keys() -> list[str]:
    """The keys of the default ``source.topics`` (the Jackal's), to null those a bag lacks."""
    try:
        from hydra import compose, initialize_config_module

        register_resolvers()
        with initialize_config_module(config_module="skidbench.conf", version_base="1.3"):
            return list(compose("extract", overrides=["source=bag", "source.root=."]).source.topics.keys())
    except Exception:  # noqa: BLE001 - the report stands without it
        return []


def main(argv: list[str] | None = None) -> None:
    """``skidbench inspect <bag or folder> ...`` (or ``source.root=<path>``): print each bag's topics and
    the proposed mapping."""
    parser = argparse.ArgumentParser(
        prog="skidbench inspect",
        description="A bag's topics (type, count, rate, start/end, gaps) and the source.topics to extract. "
        "Bags: ROS1 .bag, ROS2 .mcap/.db3 files or bag folders; a folder is searched for bags.",
    )
    parser.add_argument("paths", nargs="+", type=Path, help="bags, or folders of bags")
    parser.add_argument(
        "--typestore-ros1", default=DEFAULT_STORES["ros1"], help="for bags without definitions"
    )
    parser.add_argument(
        "--typestore-ros2", default=DEFAULT_STORES["ros2"], help="for bags without definitions"
    )
    argv = list(sys.argv[1:] if argv is None else argv)
    # `source.root=<path>` as the other stages take it
    argv = [a.split("=", 1)[1] if a.startswith("source.root=") else a for a in argv]
    args = parser.parse_args(argv)
    stores = {"ros1": args.typestore_ros1, "ros2": args.typestore_ros2}
    try:
        bags = []
        for path in args.paths:
            path = path.expanduser()
            if not path.exists():
                raise ExtractError(f"{path}: no such file or folder")
            found = [path] if path.is_file() or bag_format(path) else find_bags(path)
            if not found:
                raise ExtractError(f"{path}: no bags found (.bag, .mcap, .db3 files or ROS2 bag folders)")
            bags += found
        configured = _configured_keys()
        for i, bag in enumerate(bags):
            print(("\n" if i else "") + report(bag, inspect_bag(bag, stores), configured), flush=True)
    except SkidbenchError as exc:
        print(f"skidbench inspect: error: {one_line(str(exc))}", file=sys.stderr, flush=True)
        sys.exit(2)
