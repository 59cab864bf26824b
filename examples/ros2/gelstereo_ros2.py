"""A ROS 2 node that tracks a GelStereo-type sensor with gelstereo and publishes what it measures:
the markers as a PointCloud2 in the gel frame, the contact wrench, the slip state and the transform
from the left camera to the gel frame, in SI units. Topics, parameters and conventions: README.md
beside this file.

    .venv-ros/bin/python examples/ros2/gelstereo_ros2.py --ros-args -p recording:=data/sample/press-slide
"""

import math
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional

import numpy as np

try:
    import rclpy
    from geometry_msgs.msg import TransformStamped, WrenchStamped
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.duration import Duration
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from sensor_msgs.msg import Image, PointCloud2, PointField
    from std_msgs.msg import Bool, String
except ImportError as error:
    sys.exit(f"{error}: run scripts/setup.sh --with-ros and start the node with .venv-ros/bin/python")

import gelstereo

try:
    from tf2_msgs.msg import TFMessage
except ImportError:
    TFMessage = None

STATUS_CODES = {"tracked": 0, "predicted": 1, "lost": 2}
UNKNOWN_FLAG = 255
MM = 1e-3

# One point of the cloud; the PointFields are derived from it.
POINT = np.dtype([
    ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("id", "<u4"), ("row", "<u2"), ("col", "<u2"),
    ("dx", "<f4"), ("dy", "<f4"), ("dz", "<f4"), ("pressure", "<f4"),
    ("in_contact", "u1"), ("slip", "u1"), ("status", "u1"),
])
POINT_FIELD_TYPES = {"<f4": PointField.FLOAT32, "<u4": PointField.UINT32, "<u2": PointField.UINT16,
                     "|u1": PointField.UINT8}


@dataclass
class StereoImages:
    left: np.ndarray
    right: Optional[np.ndarray]
    stamp: object  # builtin_interfaces/Time
    seconds: float  # from the first frame


def camera_index(name: str, value) -> Optional[int]:
    """A camera parameter's device index (`2`, `'2'` or `/dev/video2`); None for -1 or ''."""
    if value in (-1, "", "-1"):
        return None
    match = re.fullmatch(r"(?:/dev/video)?(\d+)", str(value).strip())
    if match is None:
        raise ValueError(f"{name} {value!r}: expected a camera index (N or /dev/videoN); "
                         "a video file goes to recording:=")
    return int(match.group(1))


def image_from_msg(msg: Image) -> np.ndarray:
    """A sensor_msgs/Image as the pipeline takes it: grey or BGR uint8 (cv_bridge has no wheel)."""
    channels = {"mono8": 1, "bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4}.get(msg.encoding)
    if channels is None:
        raise ValueError(f"image encoding {msg.encoding!r}: expected mono8, bgr8, rgb8, bgra8 or rgba8")
    rows = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.step)
    image = rows[:, : msg.width * channels].reshape(msg.height, msg.width, channels)
    if msg.encoding.startswith("rgb"):
        image = image[..., [2, 1, 0]]
    return np.ascontiguousarray(image[..., 0] if channels == 1 else image[..., :3])


def quaternion(m: np.ndarray):
    """(x, y, z, w) of a rotation matrix."""
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        return ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4)
    i = int(np.argmax(np.diag(m)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
    q = [0.0, 0.0, 0.0]
    q[i], q[j], q[k] = s / 4, (m[j, i] + m[i, j]) / s, (m[k, i] + m[i, k]) / s
    return (*q, (m[k, j] - m[j, k]) / s)


def cloud_points(frame, grid_cols: int) -> np.ndarray:
    m = frame.markers
    known = frame.slip is not None
    points = np.zeros(len(m["row"]), POINT)
    for field, column in (("x", "X_gel_mm"), ("y", "Y_gel_mm"), ("z", "Z_gel_mm"),
                          ("dx", "dX_gel_mm"), ("dy", "dY_gel_mm"), ("dz", "dZ_gel_mm")):
        points[field] = m[column] * MM
    points["id"] = m["row"] * grid_cols + m["col"]
    points["row"], points["col"] = m["row"], m["col"]
    points["pressure"] = m["pressure_kPa"] * 1e3
    points["in_contact"] = np.where(known, m["in_contact"], UNKNOWN_FLAG)
    points["slip"] = np.where(known, m["slipping"], UNKNOWN_FLAG)
    points["status"] = [STATUS_CODES[s] for s in m["status"]]
    return points


def cloud_msg(points: np.ndarray, header) -> PointCloud2:
    msg = PointCloud2(header=header, height=1, width=len(points), is_bigendian=False, is_dense=False)
    msg.fields = [PointField(name=name, offset=offset, datatype=POINT_FIELD_TYPES[dtype.str], count=1)
                  for name, (dtype, offset) in POINT.fields.items()]
    msg.point_step = POINT.itemsize
    msg.row_step = POINT.itemsize * len(points)
    msg.data = points.tobytes()
    return msg


def wrench_msg(contact, header) -> WrenchStamped:
    msg = WrenchStamped(header=header)
    msg.wrench.force.x, msg.wrench.force.y = (float(v) for v in contact.shear_n)
    msg.wrench.force.z = -float(contact.force_n)
    msg.wrench.torque.z = float(contact.torque_nmm) * MM
    return msg


class GelstereoNode(Node):
    def __init__(self):
        super().__init__("gelstereo")
        p = self.declare
        self.source = p("source", "recording").value
        if self.source not in ("recording", "cameras", "topics"):
            raise ValueError(f"source {self.source!r}: expected recording, cameras or topics")
        self.recording = p("recording", "").value
        self.side_by_side = p("side_by_side", False).value
        self.realtime = p("realtime", True).value
        cameras = {name: p(name, default).value for name, default in (("camera_left", 0), ("camera_right", 1))}
        self.cameras = self.camera_indices(**cameras) if self.source == "cameras" else None
        self.left_image = p("left_image", "left/image_raw").value
        self.right_image = p("right_image", "right/image_raw").value
        self.camera_frame = p("camera_frame", "gelstereo_left_camera_optical_frame").value
        self.gel_frame = p("gel_frame", "gelstereo_gel").value
        self.wait_for_subscribers = p("wait_for_subscribers", 0).value
        # A file is opened at once (a bad path fails the start); cameras once subscribers are there,
        # so that the first frames are not ones read ahead while waiting.
        self.reader = self.open_recording() if self.source == "recording" else None
        self.pipeline = self.make_pipeline()
        if self.stereo_input() and not self.pipeline.is_stereo and not self.get_parameter("mono").value:
            raise ValueError("stereo input needs the parameter calibration (or mono:=true to track the left view)")
        self.grid_cols = self.pipeline.grid[1]
        self.gel_in_camera = None
        self.first_seconds = None
        self.pending = {"left": {}, "right": {}}
        self.pub_markers = self.create_publisher(PointCloud2, "markers", 10)
        self.pub_wrench = self.create_publisher(WrenchStamped, "wrench", 10)
        self.pub_slip_state = self.create_publisher(String, "slip_state", 10)
        self.pub_slipping = self.create_publisher(Bool, "slipping", 10)
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_transform = self.create_publisher(TransformStamped, "camera_to_gel", latched)
        self.pub_tf_static = TFMessage and self.create_publisher(TFMessage, "/tf_static", latched)

    def declare(self, name: str, default):
        # Numbers accept either type: `friction:=1` as well as `friction:=1.0`.
        numeric = isinstance(default, (int, float)) and not isinstance(default, bool)
        return self.declare_parameter(name, default, ParameterDescriptor(dynamic_typing=numeric))

    def make_pipeline(self) -> gelstereo.Pipeline:
        p = self.declare
        strings = {k: p(k, "").value or None for k in ("calibration", "models", "grid", "sensor", "gel", "method")}
        floats = {k: float(p(k, math.nan).value) for k in
                  ("gel_thickness_mm", "gel_modulus_kpa", "poisson", "friction", "pitch_mm")}
        floats = {k: v for k, v in floats.items() if not math.isnan(v)}
        default_calib = Path(self.recording) / "calib.yaml"
        if strings["calibration"] is None and self.source == "recording" and default_calib.is_file():
            strings["calibration"] = str(default_calib)
        calibration, models, grid, sensor = (strings.pop(k) for k in ("calibration", "models", "grid", "sensor"))
        return gelstereo.Pipeline(calibration, models, grid, sensor, threads=p("threads", 0).value,
                                  mono=p("mono", False).value, **strings, **floats)

    def camera_indices(self, camera_left, camera_right):
        """The cameras as gelstereo.open takes them: one index, or a (left, right) pair."""
        left, right = camera_index("camera_left", camera_left), camera_index("camera_right", camera_right)
        if left is None:
            raise ValueError("camera_left: expected a camera index")
        if right is not None and self.side_by_side:
            raise ValueError("side_by_side is for one camera holding both views: set camera_right:=-1")
        return left if right is None else (left, right)

    def open_recording(self) -> gelstereo.FrameReader:
        if not self.recording:
            raise ValueError("source recording needs the parameter recording "
                             "(a recording folder, a folder of images or a video file)")
        if not Path(self.recording).exists():
            raise ValueError(f"recording {self.recording}: no such file or folder")
        return gelstereo.open(self.recording, side_by_side=self.side_by_side)

    def stereo_input(self) -> bool:
        if self.source == "recording":
            return self.reader.is_stereo
        if self.source == "cameras":
            return isinstance(self.cameras, tuple) or self.side_by_side
        return bool(self.right_image)

    def frames(self) -> Iterator[StereoImages]:
        """The frames of the recording (played at their timestamps when realtime) or the cameras,
        stamped with the clock when they are taken; unreadable ones are skipped with a warning."""
        reader = self.reader if self.reader is not None else gelstereo.open(self.cameras, side_by_side=self.side_by_side)
        pace = self.realtime and self.source == "recording"
        start = time.monotonic()
        for frame in reader:
            if frame.error is not None:
                self.get_logger().warning(f"frame {frame.index} skipped: {frame.error}")
                continue
            if pace:
                time.sleep(max(0.0, start + frame.timestamp - time.monotonic()))
            yield StereoImages(frame.left, frame.right, self.get_clock().now().to_msg(), frame.timestamp)
        if self.source == "cameras":
            self.get_logger().warning(f"cameras {self.cameras}: no more frames (unplugged?)")

    def subscribe_to_images(self):
        self.create_subscription(Image, self.left_image, lambda m: self.on_image("left", m), 10)
        if self.right_image:
            self.create_subscription(Image, self.right_image, lambda m: self.on_image("right", m), 10)

    def on_image(self, side: str, msg: Image):
        """Pairs the left and right images of equal stamps (a stereo driver stamps both alike)."""
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        self.pending[side][key] = msg
        other = self.pending["right" if side == "left" else "left"]
        if self.right_image and key not in other:
            for queue in self.pending.values():
                while len(queue) > 30:
                    queue.pop(next(iter(queue)))
            return
        left = self.pending["left"].pop(key)
        right = self.pending["right"].pop(key, None)
        seconds = key[0] + key[1] * 1e-9
        self.first_seconds = seconds if self.first_seconds is None else self.first_seconds
        try:
            images = StereoImages(image_from_msg(left), None if right is None else image_from_msg(right),
                                  left.header.stamp, seconds - self.first_seconds)
            self.process(images)
        except (ValueError, gelstereo.GelstereoError) as error:
            self.get_logger().error(f"images of stamp {key[0]}.{key[1]:09d} skipped: {error}")

    def wait_for_listeners(self):
        publishers = (self.pub_markers, self.pub_wrench, self.pub_slip_state, self.pub_slipping)
        while rclpy.ok() and min(p.get_subscription_count() for p in publishers) < self.wait_for_subscribers:
            rclpy.spin_once(self, timeout_sec=0.05)

    def process(self, images: StereoImages):
        right = images.right if self.pipeline.is_stereo else None
        frame = self.pipeline.process(images.left, right, timestamp=images.seconds)
        header = PointCloud2().header
        header.stamp, header.frame_id = images.stamp, self.gel_frame
        self.publish_transform(frame, images.stamp)
        self.pub_markers.publish(cloud_msg(cloud_points(frame, self.grid_cols), header))
        self.pub_slip_state.publish(String(data=frame.slip or "unknown"))
        if frame.slip is not None:
            self.pub_slipping.publish(Bool(data=frame.slip in ("partial_slip", "gross_slip")))
        if frame.slip is not None and math.isfinite(frame.contact.force_n):
            self.pub_wrench.publish(wrench_msg(frame.contact, header))
        if frame.note:
            self.get_logger().warning(f"frame {frame.frame}: {frame.note}")

    def publish_transform(self, frame, stamp):
        """The gel frame's pose in the left camera's (the pipeline's `camera_from_gel`), once known
        (a stereo sensor, from the reference frame on) and again whenever it changes."""
        if frame.camera_from_gel is None:
            return
        pose = frame.camera_from_gel[:3]  # the gel's axes as columns, its origin (mm) as the last
        if self.gel_in_camera is not None and np.array_equal(pose, self.gel_in_camera):
            return
        self.gel_in_camera = pose
        msg = TransformStamped()
        msg.header.stamp, msg.header.frame_id, msg.child_frame_id = stamp, self.camera_frame, self.gel_frame
        t = msg.transform.translation
        t.x, t.y, t.z = (float(v) * MM for v in pose[:, 3])
        r = msg.transform.rotation
        r.x, r.y, r.z, r.w = (float(v) for v in quaternion(pose[:, :3]))
        self.pub_transform.publish(msg)
        if self.pub_tf_static:
            self.pub_tf_static.publish(TFMessage(transforms=[msg]))

    def run_stream(self):
        """A recording or the cameras: frames in turn, then (a recording's end) every message delivered."""
        self.wait_for_listeners()
        count = 0
        for images in self.frames():
            if not rclpy.ok():  # Ctrl-C
                return
            self.process(images)
            rclpy.spin_once(self, timeout_sec=0)
            count += 1
        for publisher in (self.pub_markers, self.pub_wrench, self.pub_slip_state, self.pub_slipping):
            publisher.wait_for_all_acked(Duration(seconds=5))
        self.get_logger().info(f"{count} frames published")


def main() -> int:
    rclpy.init(args=sys.argv)
    node = None
    try:
        node = GelstereoNode()
        if node.source == "topics":
            node.subscribe_to_images()
            rclpy.spin(node)
        else:
            node.run_stream()
        return 0
    except (ValueError, gelstereo.GelstereoError) as error:
        print(f"gelstereo_ros2: {error}", file=sys.stderr)
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


if __name__ == "__main__":
    sys.exit(main())
