"""The renderer's and the bag writer's shortcuts against the plain computation they replace: the faces'
pixel boxes at once against one face at a time, the noise's saturating add against a clip, and a camera
info written after another (its fields are built once per info) against its own values."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader

from skidbench.pipeline.extract.reader import ROS1, default_typestore
from skidbench.pipeline.simulate.bag import BagSink
from skidbench.pipeline.simulate.render import StereoRenderer

REPO = Path(__file__).resolve().parents[1]
SMALL = {"ground_texture_px": 1024, "ground_texel_m": 0.01, "wall_texture_px": 256}


@pytest.fixture(scope="module")
def renderer() -> StereoRenderer:
    camera = yaml.safe_load((REPO / "conf" / "robot" / "jackal.yaml").read_text())["camera"]
    return StereoRenderer(camera, 3, **SMALL)


def _faces(renderer: StereoRenderer, pose):
    """The front faces the left camera sees at ``pose`` (None when none), with their outlines."""
    T_w_c = renderer.camera_poses(*pose)[0]
    R_c_w = T_w_c[:3, :3].T
    t_c_w = -R_c_w @ T_w_c[:3, 3]
    idx, _alpha = renderer._visible_boxes(T_w_c[:2, 3])
    idx = idx[renderer._in_view(idx, R_c_w, t_c_w)]
    faces = renderer._face_geometry(idx, R_c_w, t_c_w, T_w_c[:3, 3]) if len(idx) else None
    if faces is None:
        return None, []
    return faces, [renderer._face_outline(faces, j) for j in range(len(faces.b_i))]


def test_pixel_boxes_of_all_faces_equal_each_face_alone(renderer):
    """Boxes and fillConvexPoly points computed for every face at once are those of one face at a time
    (the integer box of the outline, the outline in 1/16 pixel from the box's corner), near-plane
    clipped faces included."""
    rng = np.random.default_rng(11)
    period = renderer.period
    seen = clipped = 0
    poses = np.column_stack([rng.uniform(0, period, (150, 2)), rng.uniform(-3, 3, 150)])
    for pose in poses.tolist():
        faces, outlines = _faces(renderer, pose)
        if faces is None:
            continue
        boxes, polys = renderer._pixel_boxes(faces, outlines)
        for j, (uv, box, poly) in enumerate(zip(outlines, boxes, polys, strict=True)):
            alone = None if uv is None else renderer._pixel_box(uv)
            assert box == alone
            if alone is None:
                assert poly is None
                continue
            seen += 1
            clipped += not faces.in_front[j]
            expected = np.round((uv - [alone[0], alone[1]]) * 16).astype(np.int32)
            assert poly.dtype == np.int32 and np.array_equal(poly, expected)
    assert seen > 300 and clipped > 0


def test_noise_is_added_saturating_as_a_clip():
    """cv2.add of the uint8 image and the int16 noise is np.clip(image + noise, 0, 255) at every grey
    level and noise value."""
    img = np.repeat(np.arange(256, dtype=np.uint8)[:, None], 17, axis=1)
    noise = np.repeat(np.arange(-8, 9, dtype=np.int16)[None, :], 256, axis=0)
    expected = np.clip(img.astype(np.int16) + noise, 0, 255).astype(np.uint8)
    assert np.array_equal(cv2.add(img, noise, dtype=cv2.CV_8U), expected)


def test_camera_info_fields_follow_the_info_given(renderer, tmp_path):
    """A camera info written after another of the same side carries its own matrices, not the first's."""
    first = renderer.camera_info()["left"]
    second = dict(first, K=(2 * np.asarray(first["K"])).tolist(), width=first["width"] + 2)
    path = tmp_path / "info.bag"
    with BagSink(path, "ros1") as sink:
        for k, info in enumerate((first, first, second, first)):
            sink.camera_info("left", 1_700_000_000 * 10**9 + k, info)
    got = []
    with AnyReader([path], default_typestore=default_typestore(ROS1)) as reader:
        for conn, _t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            got.append((msg.K.tolist(), msg.width, msg.header.seq))
    want = [(np.ravel(i["K"]).tolist(), i["width"], k) for k, i in enumerate((first, first, second, first))]
    assert got == want
