"""Raw sensor_msgs/Image: decoding per encoding (row padding, byte order, Bayer patterns), extraction of
its table and files, and stereo VO on raw images against the compressed path."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from rosbags.rosbag1 import Writer

from skidbench.pipeline.extract.images import ImageDecodeError, gray8, png_bytes, raw_pixels
from skidbench.pipeline.extract.synthetic import T0_NS, _Factory, typestore_for
from skidbench.pipeline.groundtruth.stereo.vo import StereoSettings, run_stereo_vo
from skidbench.pipeline.simulate.render import StereoRenderer

REPO = Path(__file__).resolve().parents[1]
SMALL = {"ground_texture_px": 2048, "ground_texel_m": 0.005, "wall_texture_px": 512}
RNG = np.random.default_rng(11)
H, W = 6, 10


def image_msg(pixels: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False):
    """An Image-like message of ``pixels`` (H, W[, C]) with ``pad`` bytes of padding per row."""
    arr = pixels.astype(pixels.dtype.newbyteorder(">" if bigendian else "<"))
    rows = arr.reshape(arr.shape[0], -1).view(np.uint8)
    data = np.concatenate([rows, np.full((rows.shape[0], pad), 0xAB, np.uint8)], axis=1)
    return SimpleNamespace(
        encoding=encoding,
        height=pixels.shape[0],
        width=pixels.shape[1],
        step=data.shape[1],
        is_bigendian=int(bigendian),
        data=data.reshape(-1),
    )


def mosaic(bgr: np.ndarray, pattern: str) -> np.ndarray:
    """The Bayer mosaic a camera with colour filters ``pattern`` (ROS order: row 0 then row 1) records."""
    channel = {"r": 2, "g": 1, "b": 0}
    out = np.zeros(bgr.shape[:2], bgr.dtype)
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        out[dy::2, dx::2] = bgr[dy::2, dx::2, channel[pattern[k]]]
    return out


@pytest.mark.parametrize(
    "encoding, channels, dtype",
    [("mono8", 1, np.uint8), ("rgb8", 3, np.uint8), ("bgr8", 3, np.uint8), ("rgba8", 4, np.uint8),
     ("bgra8", 4, np.uint8), ("mono16", 1, np.uint16), ("rgb16", 3, np.uint16)],
)  # fmt: skip
@pytest.mark.parametrize("bigendian", [False, True])
def test_lossless_encodings_decode_to_their_exact_pixels_despite_row_padding(
    encoding, channels, dtype, bigendian
):
    shape = (H, W) if channels == 1 else (H, W, channels)
    pixels = RNG.integers(0, np.iinfo(dtype).max + 1, shape, dtype=np.int64).astype(dtype)
    msg = image_msg(pixels, encoding, pad=6, bigendian=bigendian)
    got = raw_pixels(msg)
    assert got.dtype == dtype and np.array_equal(got, pixels)
    # grey: OpenCV's own conversion of the known pixels (16-bit: their high byte, as cv_bridge)
    code = {"rgb8": cv2.COLOR_RGB2GRAY, "bgr8": cv2.COLOR_BGR2GRAY, "rgba8": cv2.COLOR_RGBA2GRAY,
            "bgra8": cv2.COLOR_BGRA2GRAY, "rgb16": cv2.COLOR_RGB2GRAY}.get(encoding)  # fmt: skip
    grey = pixels if code is None else cv2.cvtColor(pixels, code)
    want = grey if dtype == np.uint8 else (grey >> 8).astype(np.uint8)
    assert np.array_equal(gray8(msg), want)
    # a grey scene in colour (R = G = B) is that grey, exactly
    if channels >= 3:
        g = pixels[..., 0]
        flat = np.repeat(g[..., None], channels, axis=2)
        want = g if dtype == np.uint8 else (g >> 8).astype(np.uint8)
        assert np.array_equal(gray8(image_msg(flat, encoding, pad=2, bigendian=bigendian)), want)
    # extract.images=files: a lossless PNG of the pixels (colour in OpenCV's BGR order)
    png = cv2.imdecode(np.frombuffer(png_bytes(msg), np.uint8), cv2.IMREAD_UNCHANGED)
    view = {"rgb8": cv2.COLOR_RGB2BGR, "rgba8": cv2.COLOR_RGBA2BGRA, "rgb16": cv2.COLOR_RGB2BGR}.get(encoding)
    assert np.array_equal(png, pixels if view is None else cv2.cvtColor(pixels, view))


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
@pytest.mark.parametrize("bits", [8, 16])
def test_bayer_mosaics_of_a_flat_colour_demosaic_to_that_colour(pattern, bits):
    dtype = np.uint8 if bits == 8 else np.uint16
    scale = 1 if bits == 8 else 257
    bgr = np.zeros((8, 12, 3), dtype)
    bgr[:] = np.array([40, 120, 210]) * scale  # B, G, R
    msg = image_msg(mosaic(bgr, pattern), f"bayer_{pattern}{bits}", pad=4)
    want = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    want = want if bits == 8 else (want >> 8).astype(np.uint8)
    assert np.array_equal(gray8(msg), want)
    # a wrong pattern gives another grey: the pattern is honoured
    other = {"rggb": "bggr", "bggr": "rggb", "gbrg": "rggb", "grbg": "rggb"}[pattern]
    wrong = image_msg(mosaic(bgr, pattern), f"bayer_{other}{bits}", pad=4)
    assert not np.array_equal(gray8(wrong), want)


@pytest.mark.parametrize("encoding, luma_first", [("yuv422", False), ("yuv422_yuy2", True)])
def test_packed_yuv_decodes_to_its_luma(encoding, luma_first):
    """UYVY (ROS's yuv422) and YUY2: the grey image is the Y samples, whatever U and V hold."""
    y = RNG.integers(0, 256, (H, W), dtype=np.uint8)
    chroma = RNG.integers(0, 256, (H, W), dtype=np.uint8)
    pairs = np.stack([y, chroma] if luma_first else [chroma, y], axis=2)  # (H, W, 2): 2 bytes a pixel
    assert np.array_equal(gray8(image_msg(pairs, encoding, pad=4)), y)


def test_undecodable_images_raise_naming_the_problem():
    pixels = np.zeros((H, W), np.uint8)
    with pytest.raises(ImageDecodeError, match="'32FC1' is not supported"):
        gray8(image_msg(pixels, "32FC1"))
    short = image_msg(pixels, "mono8")
    short.data = short.data[:-1]
    with pytest.raises(ImageDecodeError, match="59 bytes"):
        gray8(short)
    assert png_bytes(image_msg(pixels, "yuv422")) is None  # written as .raw bytes instead
    bad = SimpleNamespace(format="jpeg", data=np.arange(10, dtype=np.uint8))
    with pytest.raises(ImageDecodeError, match="undecodable jpeg"):
        gray8(bad)


# -------------------------------------------------------------------------------------------------
# a rendered stereo drive written as compressed (PNG: lossless) and raw images of several encodings

VARIANTS = {  # name -> (topic suffix, encoding); "compressed" is the simulator's CompressedImage path
    "mono8": "mono8",
    "rgb8": "rgb8",
    "bgr8": "bgr8",
    "bayer": "bayer_rggb8",
}
N_FRAMES = 40
FPS = 15.0


def _pose(k: int) -> tuple[float, float, float]:
    # 1 m/s forward while turning at 0.4 rad/s, from (4, 3)
    t = k / FPS
    yaw = 0.3 + 0.4 * t
    return 4.0 + (np.sin(yaw) - np.sin(0.3)) / 0.4, 3.0 - (np.cos(yaw) - np.cos(0.3)) / 0.4, yaw


def _encode(grey: np.ndarray, encoding: str) -> np.ndarray:
    if encoding == "mono8":
        return grey
    if encoding.startswith("bayer_"):
        return mosaic(np.repeat(grey[..., None], 3, axis=2), encoding[6:10])
    return np.repeat(grey[..., None], 3, axis=2)  # a grey scene: R = G = B


@pytest.fixture(scope="module")
def camera_cfg() -> dict:
    return yaml.safe_load((REPO / "conf" / "robot" / "jackal.yaml").read_text())["camera"]


@pytest.fixture(scope="module")
def stereo_bag(tmp_path_factory, camera_cfg) -> Path:
    renderer = StereoRenderer(camera_cfg, 7, **SMALL)
    path = tmp_path_factory.mktemp("raw") / "drive.bag"
    ts = typestore_for("ros1")
    f = _Factory(ts)
    info = renderer.camera_info()
    with Writer(path) as writer:
        conns = {}

        def write(topic: str, msgtype: str, t: int, msg) -> None:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conns[topic], t, ts.serialize_ros1(msg, msgtype))

        for k in range(N_FRAMES):
            t = T0_NS + int(round(k / FPS * 1e9))
            twist = f("geometry_msgs/msg/Twist", linear=f.vec(0.3, 0.0, 0.0), angular=f.vec(0.0, 0.0, 0.0))
            write("/cmd_vel", "geometry_msgs/msg/Twist", t, twist)  # a dataset needs its commands
            images = dict(zip(("left", "right"), renderer.render(*_pose(k)), strict=True))
            for side, grey in images.items():
                header = f.header(t, f"{side}_optical", k)
                cam = info[side]
                write(f"/{side}/camera_info", "sensor_msgs/msg/CameraInfo", t, f(
                    "sensor_msgs/msg/CameraInfo", header=header, width=cam["width"], height=cam["height"],
                    distortion_model="plumb_bob", D=np.zeros(5), K=np.ravel(cam["K"]), R=np.eye(3).ravel(),
                    P=np.ravel(cam["P"]),
                ))  # fmt: skip
                png = np.frombuffer(cv2.imencode(".png", grey)[1].tobytes(), np.uint8)
                compressed = f("sensor_msgs/msg/CompressedImage", header=header, format="png", data=png)
                write(f"/{side}/compressed", "sensor_msgs/msg/CompressedImage", t, compressed)
                for name, encoding in VARIANTS.items():
                    pixels = _encode(grey, encoding)
                    rows = pixels.reshape(pixels.shape[0], -1)
                    pad = 8 if name == "mono8" else 0  # a padded row on one of them
                    data = np.concatenate([rows, np.zeros((rows.shape[0], pad), np.uint8)], axis=1)
                    msg = f(
                        "sensor_msgs/msg/Image",
                        header=header,
                        height=grey.shape[0],
                        width=grey.shape[1],
                        encoding=encoding,
                        is_bigendian=0,
                        step=data.shape[1],
                        data=data.reshape(-1),
                    )
                    write(f"/{side}/{name}", "sensor_msgs/msg/Image", t, msg)
    return path


def _vo(bag: Path, camera_cfg: dict, variant: str):
    topics = {
        "left_image": {"topic": f"/left/{variant}"},
        "right_image": {"topic": f"/right/{variant}"},
        "left_info": {"topic": "/left/camera_info"},
        "right_info": {"topic": "/right/camera_info"},
    }
    stats: dict = {}
    traj = run_stereo_vo(bag, StereoSettings(camera=camera_cfg, topics=topics), stats=stats)
    return traj, stats


@pytest.fixture(scope="module")
def compressed_vo(stereo_bag, camera_cfg):
    return _vo(stereo_bag, camera_cfg, "compressed")[0]


@pytest.mark.parametrize("variant", ["mono8", "rgb8", "bgr8"])
def test_vo_on_lossless_raw_images_equals_the_compressed_path_exactly(
    stereo_bag, camera_cfg, compressed_vo, variant
):
    """The same grey pixels as mono8 (padded rows), rgb8 or bgr8: the same frames, the same poses."""
    traj, stats = _vo(stereo_bag, camera_cfg, variant)
    assert stats["frames"] == N_FRAMES and len(traj) == N_FRAMES and not traj.gaps
    assert np.array_equal(traj.stamp_ns, compressed_vo.stamp_ns)
    assert np.array_equal(traj.xyz, compressed_vo.xyz) and np.array_equal(traj.quat, compressed_vo.quat)


def test_vo_on_a_bayer_mosaic_tracks_the_drive_like_the_compressed_path(
    stereo_bag, camera_cfg, compressed_vo
):
    """Demosaicing is not lossless: the poses agree within a centimetre over the 2.6 m drive, and both
    follow the rendered drive."""
    traj, _ = _vo(stereo_bag, camera_cfg, "bayer")
    assert len(traj) == N_FRAMES and not traj.gaps
    assert np.abs(traj.xyz - compressed_vo.xyz).max() < 0.01
    x0, y0, yaw0 = _pose(0)
    x, y, yaw = _pose(N_FRAMES - 1)
    c, s = np.cos(yaw0), np.sin(yaw0)
    end = np.array([c * (x - x0) + s * (y - y0), -s * (x - x0) + c * (y - y0)])  # in the first base frame
    assert np.abs(traj.xyz[-1, :2] - end).max() < 0.03
    assert np.abs(compressed_vo.xyz[-1, :2] - end).max() < 0.03


def test_raw_image_topics_extract_to_a_table_and_lossless_files(tmp_path, stereo_bag):
    from hydra import compose, initialize_config_module

    from skidbench.pipeline.extract.app import run

    with initialize_config_module(config_module="skidbench.conf", version_base="1.3"):
        cfg = compose("extract", overrides=[
            f"out_root={tmp_path}", "source=bag", f"source.root={stereo_bag}", "source.terrain=lab",
            "source.category=train", "dataset=raw", "extract.progress=false", "extract.images=files",
            "source.topics.joint_states.required=false",
            "source.topics.odom.required=false", "source.topics.imu.required=false",
            "source.topics.left_image.topic=/left/mono8",
            "source.topics.left_image.type=sensor_msgs/msg/Image",
            "source.topics.right_image.topic=/right/bayer",
            "source.topics.right_image.type=sensor_msgs/Image",  # the ROS1 spelling
        ])  # fmt: skip
    run(cfg)
    folder = tmp_path / "raw" / "extracted" / "drive"
    left = pd.read_parquet(folder / "left_image.parquet")
    assert list(left.columns) == [
        "stamp_ns", "bag_time_ns", "frame_id", "encoding", "width", "height", "step", "is_bigendian",
        "index", "nbytes",
    ]  # fmt: skip
    assert len(left) == N_FRAMES and (left["encoding"] == "mono8").all()
    assert (left["step"] == 320 + 8).all() and (left["nbytes"] == 240 * 328).all()
    assert left["index"].tolist() == list(range(N_FRAMES))
    # the files are the exact pixels: mono8 without its row padding, the Bayer mosaic as one channel
    renderer_img = cv2.imread(str(folder / "images" / "left_image" / "000003.png"), cv2.IMREAD_UNCHANGED)
    assert renderer_img.shape == (240, 320) and renderer_img.dtype == np.uint8
    right = cv2.imread(str(folder / "images" / "right_image" / "000003.png"), cv2.IMREAD_UNCHANGED)
    assert right.shape == (240, 320)
    camera = yaml.safe_load((REPO / "conf" / "robot" / "jackal.yaml").read_text())["camera"]
    l_grey, r_grey = StereoRenderer(camera, 7, **SMALL).render(*_pose(3))
    assert np.array_equal(renderer_img, l_grey)
    assert np.array_equal(right, mosaic(np.repeat(r_grey[..., None], 3, axis=2), "rggb"))
