"""The ROS 2 node against `gelstereo track`: launched on the sample recording, on the sample as a
side-by-side video, and fed the sample as image topics, its PointCloud2, WrenchStamped, slip and
transform messages carry the tables' values.

    .venv-ros/bin/python -m pytest -q examples/ros2

Each run talks on its own ROS domain, namespace and the loopback only, so runs at once do not meet.
"""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import TransformStamped, WrenchStamped
from rclpy.node import Node
from rclpy.time import Time
from rclpy.qos import DurabilityPolicy, QoSProfile
from sensor_msgs.msg import Image, PointCloud2, PointField
from std_msgs.msg import Bool, String

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data" / "sample" / "press-slide"
NODE = ROOT / "examples" / "ros2" / "gelstereo_ros2.py"
NAMESPACE = f"/gelstereo_test_{os.getpid()}"
FIELD_DTYPES = {PointField.FLOAT32: "<f4", PointField.UINT32: "<u4", PointField.UINT16: "<u2",
                PointField.UINT8: "u1"}
TIMEOUT_S = 60


@pytest.fixture(scope="module", autouse=True)
def ros_domain():
    """A domain of this run's own, discovery on this machine only; one rclpy context for the module."""
    os.environ["ROS_DOMAIN_ID"] = str(1 + os.getpid() % 100)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    rclpy.init()
    yield
    rclpy.shutdown()


@pytest.fixture(scope="module")
def tables(gelstereo_bin, tmp_path_factory):
    """`gelstereo track` on the sample with every default: markers rows by frame, frames rows, gel.json."""
    out = tmp_path_factory.mktemp("track")
    subprocess.run([str(gelstereo_bin), "track", "--quiet", "--no-ply", "--overlay-every", "0",
                    "--out", str(out), str(SAMPLE)], check=True)
    markers = defaultdict(list)
    with open(out / "markers.csv") as m:
        for row in csv.DictReader(m):
            markers[int(row["frame"])].append(row)
    with open(out / "frames.csv") as f:
        frames = list(csv.DictReader(f))
    return markers, frames, json.loads((out / "gel.json").read_text())["gel_frame_in_left_camera"]


class Listener(Node):
    """Everything the node publishes, in arrival order."""

    def __init__(self):
        super().__init__(f"listener_{os.getpid()}")
        self.got = defaultdict(list)
        deep = QoSProfile(depth=100)
        for topic, kind in (("markers", PointCloud2), ("wrench", WrenchStamped), ("slip_state", String),
                            ("slipping", Bool)):
            self.create_subscription(kind, f"{NAMESPACE}/{topic}", self.got[topic].append, deep)
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(TransformStamped, f"{NAMESPACE}/camera_to_gel", self.got["camera_to_gel"].append,
                                 latched)

    def spin_until(self, done, what: str):
        deadline = time.monotonic() + TIMEOUT_S
        while not done():
            assert time.monotonic() < deadline, f"timed out waiting for {what}: {dict(self.got)}"
            rclpy.spin_once(self, timeout_sec=0.05)


def launch_node(*params: str) -> subprocess.Popen:
    args = [sys.executable, str(NODE), "--ros-args", "-r", f"__ns:={NAMESPACE}"]
    for param in params:
        args += ["-p", param]
    # Its own process group, so the finally of each test ends the node and nothing it started.
    return subprocess.Popen(args, start_new_session=True)


def stop(process: subprocess.Popen):
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGINT)
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()


def cloud_array(msg: PointCloud2) -> np.ndarray:
    """The cloud's points as a structured array, read through its PointFields."""
    dtype = np.dtype({"names": [f.name for f in msg.fields],
                      "formats": [FIELD_DTYPES[f.datatype] for f in msg.fields],
                      "offsets": [f.offset for f in msg.fields], "itemsize": msg.point_step})
    assert not msg.is_bigendian and msg.height == 1
    return np.frombuffer(bytes(msg.data), dtype, count=msg.width)


def column(rows, name: str, scale: float = 1.0) -> np.ndarray:
    return np.array([float(r[name]) * scale if r[name] else np.nan for r in rows])


def check_cloud(msg: PointCloud2, rows: list, frame: dict, gel_frame: str):
    points = cloud_array(msg)
    assert msg.header.frame_id == gel_frame
    assert len(points) == len(rows) == 529
    np.testing.assert_array_equal(points["row"], [int(r["row"]) for r in rows])
    np.testing.assert_array_equal(points["col"], [int(r["col"]) for r in rows])
    np.testing.assert_array_equal(points["id"], points["row"].astype(int) * 23 + points["col"])
    for field, name in (("x", "X_gel_mm"), ("y", "Y_gel_mm"), ("z", "Z_gel_mm"),
                        ("dx", "dX_gel_mm"), ("dy", "dY_gel_mm"), ("dz", "dZ_gel_mm")):
        # mm in the table, m in the cloud; float32 keeps about 1 nm at the gel's few cm.
        np.testing.assert_allclose(points[field], column(rows, name, 1e-3), rtol=0, atol=1e-8, equal_nan=True)
    np.testing.assert_allclose(points["pressure"], column(rows, "pressure_kPa", 1e3), rtol=1e-6, atol=1e-3)
    np.testing.assert_array_equal(points["in_contact"], [int(r["in_contact"]) for r in rows])
    np.testing.assert_array_equal(points["slip"], [int(r["slipping"]) for r in rows])
    codes = {"tracked": 0, "predicted": 1, "lost": 2}
    np.testing.assert_array_equal(points["status"], [codes[r["status"]] for r in rows])
    assert frame["contact"] in ("0", "1")


def check_wrench(msg: WrenchStamped, frame: dict, gel_frame: str):
    assert msg.header.frame_id == gel_frame
    f, t = msg.wrench.force, msg.wrench.torque
    # The force on the gel: the shear along x, y and the normal force into it, along -z.
    assert (f.x, f.y, f.z) == pytest.approx(
        (float(frame["shear_x_N"]), float(frame["shear_y_N"]), -float(frame["force_N"])), abs=1e-6)
    assert (t.x, t.y, t.z) == pytest.approx((0.0, 0.0, float(frame["torque_Nmm"]) * 1e-3), abs=1e-9)


def rotation_of(q) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@pytest.fixture(scope="module")
def side_by_side_video(tmp_path_factory) -> Path:
    """The sample as one video, each frame its left and right views side by side, coded losslessly
    (FFV1): the node reads the same pixels as from the images."""
    path = tmp_path_factory.mktemp("video") / "press-slide.mkv"
    names = sorted(p.name for p in (SAMPLE / "left").iterdir())
    writer = None
    for name in names:
        both = np.hstack([cv2.imread(str(SAMPLE / side / name)) for side in ("left", "right")])
        if writer is None:
            writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, both.shape[1::-1])
            assert writer.isOpened(), "OpenCV cannot write FFV1 video"
        writer.write(both)
    writer.release()
    return path


def source_params(source: str, request) -> list:
    if source == "recording":
        return [f"recording:={SAMPLE}"]
    video = request.getfixturevalue("side_by_side_video")
    return [f"recording:={video}", "side_by_side:=true", f"calibration:={SAMPLE / 'calib.yaml'}"]


@pytest.mark.parametrize("source", ["recording", "video"])
def test_the_node_publishes_the_sample_as_gelstereo_track_tracks_it(tables, source, request):
    markers, frames, gel = tables
    listener = Listener()
    node = launch_node(*source_params(source, request), "wait_for_subscribers:=1",
                       "camera_frame:=left_optical", "gel_frame:=gel")
    try:
        listener.spin_until(lambda: node.poll() is not None and len(listener.got["markers"]) >= len(frames),
                            "the node to publish every frame and exit")
        assert node.returncode == 0
        for _ in range(10):  # what is still in flight
            rclpy.spin_once(listener, timeout_sec=0.05)
    finally:
        stop(node)
        listener.destroy_node()
    got = listener.got
    assert len(frames) == 40 and len(got["markers"]) == len(got["wrench"]) == len(got["slip_state"]) == 40
    for k, frame in enumerate(frames):
        check_cloud(got["markers"][k], markers[k], frame, "gel")
        check_wrench(got["wrench"][k], frame, "gel")
        assert got["slip_state"][k].data == frame["slip"]
        assert got["slipping"][k].data == (frame["slip"] in ("partial_slip", "gross_slip"))
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in got["markers"]]
    assert stamps == sorted(stamps)
    # The sample presses and slides: the messages carry force and slip, not only zeros.
    assert max(-w.wrench.force.z for w in got["wrench"]) > 1.0 and any(m.data for m in got["slipping"])
    transform = got["camera_to_gel"][-1]
    assert (transform.header.frame_id, transform.child_frame_id) == ("left_optical", "gel")
    t = transform.transform.translation
    np.testing.assert_allclose([t.x, t.y, t.z], np.array(gel["origin_mm"]) * 1e-3, atol=1e-9)
    axes = np.column_stack([gel["x_axis"], gel["y_axis"], gel["z_axis"]])
    np.testing.assert_allclose(rotation_of(transform.transform.rotation), axes, atol=1e-7)


def image_msg(image: np.ndarray, encoding: str, stamp) -> Image:
    msg = Image(height=image.shape[0], width=image.shape[1], encoding=encoding, step=image.shape[1] * 3)
    msg.header.stamp = stamp
    msg.data = np.ascontiguousarray(image).tobytes()
    return msg


def test_the_node_tracks_image_topics_as_gelstereo_track_tracks_the_recording(tables):
    """Left views as bgr8, right as rgb8 (the node turns them back), paired by stamp."""
    markers, frames, _ = tables
    count = 5
    listener = Listener()
    left_pub = listener.create_publisher(Image, f"{NAMESPACE}/cam/left", QoSProfile(depth=count))
    right_pub = listener.create_publisher(Image, f"{NAMESPACE}/cam/right", QoSProfile(depth=count))
    node = launch_node("source:=topics", "left_image:=cam/left", "right_image:=cam/right",
                       f"calibration:={SAMPLE / 'calib.yaml'}")
    try:
        listener.spin_until(
            lambda: left_pub.get_subscription_count() and right_pub.get_subscription_count()
            and listener.count_publishers(f"{NAMESPACE}/markers"), "the node's image subscriptions")
        names = sorted(p.name for p in (SAMPLE / "left").iterdir())[:count]
        for k, name in enumerate(names):
            stamp = Time(seconds=100 + k / 30).to_msg()
            left = cv2.imread(str(SAMPLE / "left" / name))
            right = cv2.imread(str(SAMPLE / "right" / name))
            right_pub.publish(image_msg(right[..., ::-1], "rgb8", stamp))
            left_pub.publish(image_msg(left, "bgr8", stamp))
        listener.spin_until(lambda: len(listener.got["markers"]) >= count, f"{count} clouds")
    finally:
        stop(node)
        listener.destroy_node()
    assert node.returncode == 0
    for k in range(count):
        check_cloud(listener.got["markers"][k], markers[k], frames[k], "gelstereo_gel")
        assert listener.got["markers"][k].header.stamp == Time(seconds=100 + k / 30).to_msg()


def test_the_node_names_a_camera_it_cannot_open():
    node = subprocess.run([sys.executable, str(NODE), "--ros-args", "-r", f"__ns:={NAMESPACE}",
                           "-p", "source:=cameras", "-p", "camera_left:=97", "-p", "camera_right:=-1"],
                          capture_output=True, text=True, timeout=TIMEOUT_S)
    assert node.returncode == 1
    assert "camera 97 cannot be opened" in node.stderr
