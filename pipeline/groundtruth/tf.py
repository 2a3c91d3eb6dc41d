"""Ground truth from /tf and /tf_static: the pose of a ``child`` frame in a ``parent`` frame, composed
through the TF tree recorded in the extracted TF tables (``tf2_msgs/msg/TFMessage``, one row per
transform; CONTRIBUTING.md "Extracted tables").

How the chain is composed (tf2's semantics, without extrapolation):
- frame names are compared without a leading ``/`` (ROS1's ``/odom`` is ``odom``);
- the chain is the path between ``parent`` and ``child`` in the tree of the edges seen, walked in either
  direction (an edge walked from child to parent is inverted);
- a static edge (published on /tf_static) holds at every time: its last value is applied once;
- the output stamps are those of the child-most dynamic edge of the chain; every other dynamic edge is
  interpolated at them (linear in translation, slerp in rotation), never extrapolated: a stamp outside
  an edge's samples, or between two samples further apart than ``edge_gap_s``, is dropped, and a hole it
  leaves inside the trajectory is a gap (as are holes over ``max_gap_s`` between the output stamps);
- a frame not in the tree, or two frames in separate trees, is a one-line error listing the frames.

Reading streams the tables in record batches and keeps only the rows of the chain's edges.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from skidbench.pipeline.core.errors import GroundTruthError
from skidbench.pipeline.core.geometry import matrix_to_quaternion, quaternion_slerp, se3_inverse, se3_matrix
from skidbench.pipeline.core.timesync import bracket
from skidbench.pipeline.groundtruth.pose_topic import clean_poses
from skidbench.pipeline.groundtruth.trajectory import Trajectory

log = logging.getLogger(__name__)

TF_KEY_COLUMNS = ("parent", "child")
POSE = ["x", "y", "z", "qx", "qy", "qz", "qw"]


def frame_name(name: str) -> str:
    """tf2's frame id: without surrounding blanks and leading slashes."""
    return str(name).strip().lstrip("/")


def is_tf_table(path: Path) -> bool:
    """Whether an extracted table holds TF edges (it has ``parent`` and ``child`` columns)."""
    names = set(pq.read_schema(path).names)
    return all(c in names for c in TF_KEY_COLUMNS)


@dataclass(frozen=True)
class Link:
    """One step of a chain: the edge ``parent -> child`` as published, walked forwards (``T_parent_child``)
    or backwards (its inverse)."""

    parent: str
    child: str
    forward: bool
    static: bool


class TFTree:
    """The edges seen: ``(parent, child) -> static``. An edge with both static and dynamic rows counts as
    dynamic (its dynamic rows are used)."""

    def __init__(self, edges: Iterable[tuple[str, str, bool]]):
        self.edges: dict[tuple[str, str], bool] = {}
        for parent, child, static in edges:
            key = (frame_name(parent), frame_name(child))
            self.edges[key] = self.edges.get(key, True) and bool(static)
        parents: dict[str, list[str]] = {}
        for p, c in self.edges:
            parents.setdefault(c, []).append(p)
        self.multi_parent = {c: ps for c, ps in parents.items() if len(ps) > 1}

    @property
    def frames(self) -> list[str]:
        return sorted({f for edge in self.edges for f in edge})

    def chain(self, parent: str, child: str, where: str) -> list[Link]:
        """The links from ``parent`` to ``child`` (breadth-first: the shortest path of the tree)."""
        parent, child = frame_name(parent), frame_name(child)
        frames = self.frames
        listing = ", ".join(frames) or "none"
        for role, frame in (("parent", parent), ("child", child)):
            if frame not in frames:
                raise GroundTruthError(
                    f"{where}: TF frame {frame!r} not found (frames: {listing}); "
                    f"set groundtruth.pose_topic.{role}"
                )
        if parent == child:
            raise GroundTruthError(f"{where}: TF parent and child are the same frame {parent!r}")
        adjacent: dict[str, list[Link]] = {}
        for (p, c), static in self.edges.items():
            adjacent.setdefault(p, []).append(Link(p, c, True, static))
            adjacent.setdefault(c, []).append(Link(p, c, False, static))
        came: dict[str, Link | None] = {parent: None}
        queue = deque([parent])
        while queue and child not in came:
            frame = queue.popleft()
            for link in adjacent.get(frame, []):
                nxt = link.child if link.forward else link.parent
                if nxt not in came:
                    came[nxt] = link
                    queue.append(nxt)
        if child not in came:
            reach = sorted(came)
            raise GroundTruthError(
                f"{where}: no TF chain from {parent!r} to {child!r}: they are in separate trees "
                f"({parent!r} connects to: {', '.join(reach)}; frames: {listing})"
            )
        links: list[Link] = []
        frame = child
        while came[frame] is not None:
            link = came[frame]
            links.append(link)
            frame = link.parent if link.forward else link.child
        links.reverse()
        for link in links:
            if link.child in self.multi_parent:
                log.warning(
                    "%s: TF frame %r has several parents (%s); the edge from %r is used",
                    where, link.child, ", ".join(self.multi_parent[link.child]), link.parent,
                )  # fmt: skip
        return links


def _edge_rows(df: pd.DataFrame, link: Link) -> pd.DataFrame:
    rows = df[(df["_parent"] == link.parent) & (df["_child"] == link.child)]
    if not link.static:
        rows = rows[~rows["static"].to_numpy(dtype=bool)]
    return rows


def static_transform(rows: pd.DataFrame, link: Link, where: str) -> np.ndarray:
    """A static edge's transform ``T_parent_child`` (4x4): its last value (a re-published static
    transform that changed is logged; tf2 keeps the latest too)."""
    values = rows[POSE].to_numpy(dtype=float)
    if len(values) > 1 and np.ptp(values, axis=0).max() > 1e-9:
        log.warning(
            "%s: static TF %s -> %s was published with %d different values; the last is used",
            where, link.parent, link.child, len(np.unique(values, axis=0)),
        )  # fmt: skip
    last = values[-1]
    return se3_matrix(last[:3], last[3:] / np.linalg.norm(last[3:]))


def dynamic_samples(rows: pd.DataFrame, stamp: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A dynamic edge's samples in time order, a duplicated stamp kept once (the first):
    ``(stamp_ns (M,), xyz (M, 3), quat (M, 4))``."""
    t = rows[stamp].to_numpy(dtype=np.int64)
    order = np.argsort(t, kind="stable")
    t = t[order]
    first = np.concatenate([[True], np.diff(t) != 0])
    values = rows[POSE].to_numpy(dtype=float)[order][first]
    quat = values[:, 3:] / np.linalg.norm(values[:, 3:], axis=1, keepdims=True)
    return t[first], values[:, :3], quat


def interpolate_edge(
    stamp_ns: np.ndarray, xyz: np.ndarray, quat: np.ndarray, t: np.ndarray, max_gap_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """One edge's transforms at times ``t`` (N,) from its samples (M,): linear in translation, slerp in
    rotation. Returns ``(T (N, 4, 4), valid (N,))``; ``valid`` is False outside the samples (no
    extrapolation) and between two samples more than ``max_gap_ns`` apart (unless ``t`` is a sample)."""
    t = np.asarray(t, dtype=np.int64)
    i, frac, valid = bracket(stamp_ns, t, max_gap_ns, trust_samples=True)
    if len(stamp_ns) == 1:
        return np.broadcast_to(se3_matrix(xyz[0], quat[0]), (len(t), 4, 4)).copy(), valid
    pos = xyz[i] + frac[:, None] * (xyz[i + 1] - xyz[i])
    rot = quaternion_slerp(quat[i], quat[i + 1], frac)
    return se3_matrix(pos, rot), valid


def compose_chain(
    df: pd.DataFrame,
    links: Sequence[Link],
    where: str,
    max_gap_s: float,
    stamp: str = "bag_time_ns",
    edge_gap_s: float | None = None,
) -> Trajectory:
    """Compose ``links`` (from :meth:`TFTree.chain`) over the TF rows ``df`` into the trajectory of the
    chain's last frame in its first (module docstring). ``df`` needs ``parent child static``, the pose
    columns and ``stamp``."""
    if stamp not in df.columns:
        raise GroundTruthError(f"{where}: no {stamp} column; set groundtruth.pose_topic.stamp")
    names = {n: frame_name(n) for n in pd.unique(pd.concat([df["parent"], df["child"]]))}
    df = df.assign(_parent=df["parent"].map(names), _child=df["child"].map(names))
    edge_gap_ns = int(round((max_gap_s if edge_gap_s is None else edge_gap_s) * 1e9))
    dynamic = [k for k, link in enumerate(links) if not link.static]
    if not dynamic:
        names = " -> ".join(
            [links[0].parent if links[0].forward else links[0].child] + [_end(x) for x in links]
        )
        raise GroundTruthError(f"{where}: the TF chain {names} is static (no moving edge to take poses from)")
    driver = dynamic[-1]  # the child-most dynamic edge: its stamps are the trajectory's
    t, xyz, quat = dynamic_samples(_edge_rows(df, links[driver]), stamp)
    keep = np.ones(len(t), dtype=bool)
    transforms = []
    for k, link in enumerate(links):
        rows = _edge_rows(df, link)
        if link.static:
            T = static_transform(rows, link, where)[None]
        elif k == driver:
            T = se3_matrix(xyz, quat)
        else:
            T, valid = interpolate_edge(*dynamic_samples(rows, stamp), t, edge_gap_ns)
            if not valid.all():
                log.info(
                    "%s: %d of %d poses dropped where TF %s -> %s has no samples within %.3f s",
                    where, int((~valid).sum()), len(t), link.parent, link.child, edge_gap_ns * 1e-9,
                )  # fmt: skip
            keep &= valid
        transforms.append(T if link.forward else se3_inverse(T))
    pose = transforms[0]
    for T in transforms[1:]:
        pose = pose @ T
    pose = np.broadcast_to(pose, (len(t), 4, 4))[keep]
    # a run of dropped stamps inside the trajectory breaks it at the next kept stamp
    breaks = (keep & np.concatenate([[False], ~keep[:-1]]))[keep]
    return clean_poses(
        t[keep], pose[:, :3, 3], matrix_to_quaternion(pose[:, :3, :3]), where, max_gap_s, breaks=breaks
    )


def _end(link: Link) -> str:
    return link.child if link.forward else link.parent


def compose_tf(
    df: pd.DataFrame,
    parent: str,
    child: str,
    where: str,
    max_gap_s: float,
    stamp: str = "bag_time_ns",
    edge_gap_s: float | None = None,
) -> Trajectory:
    """The trajectory of ``child`` in ``parent`` from a TF table ``df`` (all of its edges)."""
    tree = TFTree(zip(df["parent"], df["child"], df["static"], strict=True))
    return compose_chain(df, tree.chain(parent, child, where), where, max_gap_s, stamp, edge_gap_s)


_BATCH = 1 << 16


def read_tf_trajectory(
    paths: Sequence[Path],
    parent: str | None,
    child: str | None,
    max_gap_s: float,
    stamp: str = "bag_time_ns",
    edge_gap_s: float | None = None,
) -> Trajectory:
    """The trajectory of ``child`` in ``parent`` from extracted TF tables (``tf``, ``tf_static``: their
    edges are merged). Streams: a first pass reads the edge names, a second only the chain's rows."""
    paths = [Path(p) for p in paths]
    where = str(paths[0])
    pairs: set[tuple[str, str, bool]] = set()
    for path in paths:
        for batch in pq.ParquetFile(path).iter_batches(_BATCH, columns=["parent", "child", "static"]):
            unique = pa.Table.from_batches([batch]).group_by(["parent", "child", "static"]).aggregate([])
            pairs.update(zip(*(unique[c].to_pylist() for c in ("parent", "child", "static")), strict=True))
    tree = TFTree(pairs)
    if not parent or not child:
        raise GroundTruthError(
            f"{where}: a TF table needs the frames to compose (frames: {', '.join(tree.frames) or 'none'}); "
            "set groundtruth.pose_topic.parent and groundtruth.pose_topic.child"
        )
    links = tree.chain(parent, child, where)
    wanted = {(link.parent, link.child) for link in links}
    # the names as published ("/odom" and "odom" are one frame) of the chain's edges
    raw = sorted({(p, c) for p, c, _ in pairs if (frame_name(p), frame_name(c)) in wanted})
    columns = ["parent", "child", stamp, *POSE, "static"]
    parts = []
    for path in paths:
        if stamp not in pq.read_schema(path).names:
            raise GroundTruthError(f"{path}: no {stamp} column; set groundtruth.pose_topic.stamp")
        for batch in pq.ParquetFile(path).iter_batches(_BATCH, columns=columns):
            mask = None
            for p, c in raw:
                edge = pc.and_(pc.equal(batch["parent"], p), pc.equal(batch["child"], c))
                mask = edge if mask is None else pc.or_(mask, edge)
            part = batch.filter(mask)
            if part.num_rows:
                parts.append(part.to_pandas())
    df = pd.concat(parts, ignore_index=True)
    return compose_chain(df, links, where, max_gap_s, stamp, edge_gap_s)
