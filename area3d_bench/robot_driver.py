"""A robot stack nobody wrote for AREA3D: an RGB-D camera driver and the odometry of the body it is
mounted on, as a plain rclpy process that imports nothing from the project (rclpy, the standard
messages, tf2_msgs, numpy and mujoco only). The robot tests and `area3d bench robot` run it.

    python robot_driver.py '{"scene": "path/to/scene.xml", "readers": {"/odom": 2, ...}}'

It plays a RealSense-like driver: colour bgr8 and depth 16UC1 in millimetres (registered to the
colour image, 0 = no return) at 848x480 with an 87 degree horizontal field of view on the topics a
RealSense driver uses (/camera/camera/color/image_raw, /camera/camera/aligned_depth_to_color/
image_raw, /camera/camera/color/camera_info), all best effort (the sensor-data profile), and
nav_msgs/Odometry of `base_link` in `odom` at 50 Hz on /odom, best effort too. The camera is
mounted on the body by a fixed transform published on /tf_static (base_link -> camera_link ->
camera_color_optical_frame). The scene is rendered with MuJoCo from the MJCF file itself.

A goal (geometry_msgs/PoseStamped on /driver/goal: where the camera's optical frame should be, in
the driver's fixed frame) moves the body there over `move_s` seconds, odometry flowing meanwhile;
once it has stood still for a few odometry periods, the camera captures: the image is stamped
with the driver's clock at that moment, independently of the odometry's stamps.
/driver/captured (std_msgs/String, reliable) then says {"stamp_ns", "goal"}.

Options (the JSON argument):
- `stream_hz` > 0: the camera streams at that rate all the time, while the body moves and at
  rest, as real drivers do; the capture reported is the first frame after the body stood still.
- `tf`: poses go out on /tf instead of /odom: map -> odom (10 Hz, a localisation offset of
  0.3 m, -0.2 m and 5 degrees of yaw) and odom -> base_link (50 Hz); goals are in `map`.
- `loss`: each image and camera info is left unpublished with this probability (seeded by
  `seed`), as a best-effort link loses parts.
- `render_scale` < 1: render at that fraction of 848x480 and publish 848x480 (nearest
  neighbour), so that a CPU-rendered stream keeps its rate.
Runs until SIGINT or SIGTERM.
"""

import json
import os
import signal
import sys
import time

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import rclpy  # noqa: E402
from builtin_interfaces.msg import Time  # noqa: E402
from geometry_msgs.msg import PoseStamped, TransformStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import (  # noqa: E402
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.signals import SignalHandlerOptions  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

WIDTH, HEIGHT, HFOV_DEG = 848, 480, 87.0
MAX_RANGE = 5.0
ODOM_HZ = 50.0
MAP_HZ = 10.0
MOVE_S = 0.5
SETTLE_TICKS = 3  # odometry periods the body stands still before a capture
READERS_FOR_S = 1.0  # the readers have had the odometry this long before the first capture
COLOR = "/camera/camera/color/image_raw"
DEPTH = "/camera/camera/aligned_depth_to_color/image_raw"
INFO = "/camera/camera/color/camera_info"
ODOM = "/odom"
OPTICAL = "camera_color_optical_frame"
# map -> odom: where localisation puts the odometry's origin (tf option)
MAP_ODOM_XY = (0.3, -0.2)
MAP_ODOM_YAW_DEG = 5.0
# base_link -> camera_link: 10 cm ahead, 25 cm up, pitched down 10 degrees (REP 103 axes)
LINK_XYZ = (0.10, 0.0, 0.25)
LINK_PITCH_DEG = 10.0
# camera_link (x forward, y left, z up) -> the optical frame (z forward, x right, y down)
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
# MuJoCo cameras look along -z with y up
MJ_FROM_OPTICAL = np.diag([1.0, -1.0, -1.0])
SHORT_STALL_S = 0.5
RELIABLE = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
TF_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
LATCHED = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


def quaternion(R):
    """(x, y, z, w) of a rotation matrix, w >= 0."""
    m = np.asarray(R, dtype=float)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    q = np.array(q) / np.linalg.norm(q)
    return -q if q[3] < 0 else q


def rotation(q):
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def pose_matrix(pose):
    T = np.eye(4)
    o = pose.orientation
    T[:3, :3] = rotation(np.array([o.x, o.y, o.z, o.w]) / np.linalg.norm([o.x, o.y, o.z, o.w]))
    T[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    return T


def blend(A, B, u):
    """Pose a fraction u of the way from A to B (linear position, normalised quaternion blend)."""
    qa, qb = quaternion(A[:3, :3]), quaternion(B[:3, :3])
    if np.dot(qa, qb) < 0:
        qb = -qb
    q = (1 - u) * qa + u * qb
    T = np.eye(4)
    T[:3, :3] = rotation(q / np.linalg.norm(q))
    T[:3, 3] = (1 - u) * A[:3, 3] + u * B[:3, 3]
    return T


def stamp_of(ns):
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def transform(parent, child, T, ns):
    msg = TransformStamped()
    msg.header.frame_id, msg.header.stamp, msg.child_frame_id = parent, stamp_of(ns), child
    t, q = msg.transform.translation, msg.transform.rotation
    t.x, t.y, t.z = map(float, T[:3, 3])
    q.x, q.y, q.z, q.w = map(float, quaternion(T[:3, :3]))
    return msg


class Camera:
    """MuJoCo RGB-D rendering of the MJCF scene at an optical-frame pose."""

    def __init__(self, scene_path, scale=1.0):
        self.fx = (WIDTH / 2) / np.tan(np.radians(HFOV_DEG) / 2)
        self.scale = int(round(1.0 / scale)) if scale < 1.0 else 1
        width, height = WIDTH // self.scale, HEIGHT // self.scale
        fovy = 2 * np.degrees(np.arctan((HEIGHT / 2) / self.fx))
        spec = mujoco.MjSpec.from_file(scene_path)
        spec.visual.global_.offwidth = max(WIDTH, spec.visual.global_.offwidth)
        spec.visual.global_.offheight = max(HEIGHT, spec.visual.global_.offheight)
        spec.worldbody.add_camera(name="driver_camera", fovy=fovy)
        self.model = spec.compile()
        extent = self.model.stat.extent
        self.model.vis.map.znear = 0.01 / extent
        self.model.vis.map.zfar = 2 * MAX_RANGE / extent
        self.data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, self.data)
        self.camera = self.model.camera("driver_camera").id
        self.renderer = mujoco.Renderer(self.model, height, width)

    def render(self, T):
        """(bgr (H, W, 3) uint8, depth (H, W) uint16 millimetres, 0 = no return)."""
        self.data.cam_xpos[self.camera] = T[:3, 3]
        self.data.cam_xmat[self.camera] = (T[:3, :3] @ MJ_FROM_OPTICAL).ravel()
        self.renderer.disable_depth_rendering()
        self.renderer.update_scene(self.data, camera=self.camera)
        rgb = self.renderer.render().copy()
        self.renderer.enable_depth_rendering()
        self.renderer.update_scene(self.data, camera=self.camera)
        metres = self.renderer.render().astype(np.float64)
        mm = np.where((metres > 0) & (metres < MAX_RANGE), np.rint(metres * 1000.0), 0.0)
        bgr, mm = rgb[..., ::-1], mm.astype(np.uint16)
        if self.scale > 1:  # nearest neighbour back to the published size
            bgr = bgr.repeat(self.scale, 0).repeat(self.scale, 1)
            mm = mm.repeat(self.scale, 0).repeat(self.scale, 1)
        return np.ascontiguousarray(bgr), np.ascontiguousarray(mm)

    def info(self, ns):
        msg = CameraInfo()
        msg.header.frame_id, msg.header.stamp = OPTICAL, stamp_of(ns)
        msg.width, msg.height = WIDTH, HEIGHT
        msg.distortion_model = "plumb_bob"
        msg.d = [0.0] * 5
        msg.k = [self.fx, 0.0, WIDTH / 2, 0.0, self.fx, HEIGHT / 2, 0.0, 0.0, 1.0]
        msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        msg.p = [self.fx, 0.0, WIDTH / 2, 0.0, 0.0, self.fx, HEIGHT / 2, 0.0, 0.0, 0.0, 1.0, 0.0]
        return msg


def image(array, encoding, ns):
    msg = Image()
    msg.header.frame_id, msg.header.stamp = OPTICAL, stamp_of(ns)
    msg.height, msg.width = array.shape[:2]
    msg.encoding = encoding
    msg.step = array.shape[1] * array.itemsize * (array.shape[2] if array.ndim == 3 else 1)
    msg.data = array.tobytes()
    return msg


class Driver(Node):
    def __init__(self, config):
        super().__init__("robot_driver")
        self.camera = Camera(config["scene"], config.get("render_scale", 1.0))
        self.readers = config.get("readers", {})
        self.stream_hz = float(config.get("stream_hz", 0.0))
        self.use_tf = bool(config.get("tf", False))
        self.loss = float(config.get("loss", 0.0))
        self.move_s = float(config.get("move_s", MOVE_S))
        self.rng = np.random.default_rng(config.get("seed", 0))
        self.fixed = "map" if self.use_tf else "odom"
        yaw = np.radians(MAP_ODOM_YAW_DEG)
        self.T_map_odom = np.eye(4)
        self.T_map_odom[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        self.T_map_odom[:2, 3] = MAP_ODOM_XY
        self.frames_published = 0
        self.parts_lost = 0
        self.frames_late = 0  # frame slots the renderer was too slow for (a camera's drops)
        # of those, the ones inside a gap of at most SHORT_STALL_S between two colour images that
        # went out (a stream's drops; a longer gap, two stalls with the image between them lost
        # too, reads as the camera pausing to whoever counts gaps in the colour stamps)
        self.frames_late_short = 0
        self._late_pending = 0  # late slots since the last colour image that went out
        self._last_color_ns: int | None = None
        T_link = np.eye(4)
        pitch = np.radians(LINK_PITCH_DEG)
        T_link[:3, :3] = [
            [np.cos(pitch), 0, np.sin(pitch)],
            [0, 1, 0],
            [-np.sin(pitch), 0, np.cos(pitch)],
        ]
        T_link[:3, 3] = LINK_XYZ
        T_optical = np.eye(4)
        T_optical[:3, :3] = R_LINK_OPTICAL
        self.T_base_camera = T_link @ T_optical
        self.body = np.eye(4)
        self.motion = None  # (start pose, goal pose, start time, goal stamp)
        self.settled = 0
        self.read_since = None
        sensor = qos_profile_sensor_data
        self.pubs = {
            COLOR: self.create_publisher(Image, COLOR, sensor),
            DEPTH: self.create_publisher(Image, DEPTH, sensor),
            INFO: self.create_publisher(CameraInfo, INFO, sensor),
            ODOM: self.create_publisher(Odometry, ODOM, sensor),
        }
        self.captured = self.create_publisher(String, "/driver/captured", RELIABLE)
        self.tf_static = self.create_publisher(TFMessage, "/tf_static", LATCHED)
        # /tf as tf2's TransformBroadcaster publishes it: reliable, 100 deep
        self.tf = self.create_publisher(TFMessage, "/tf", TF_QOS)
        now = self.get_clock().now().nanoseconds
        self.tf_static.publish(
            TFMessage(
                transforms=[
                    transform("base_link", "camera_link", T_link, now),
                    transform("camera_link", OPTICAL, T_optical, now),
                ]
            )
        )
        self.create_subscription(PoseStamped, "/driver/goal", self.on_goal, RELIABLE)
        self.create_timer(1.0 / ODOM_HZ, self.tick)
        if self.use_tf:
            self.create_timer(1.0 / MAP_HZ, self.tick_map)
        self.stream_ns = 0  # stamp of the last streamed frame
        self.settled_ns = None  # when the body stood still at the goal (streaming)
        # a camera's frame clock: frame k is exposed at t0 + k / stream_hz, whatever the renderer
        # does; a slot it is too late for is a frame dropped (counted, as a driver counts them)
        self.slot = None  # (t0 in ns, t0 monotonic, last slot)
        if self.stream_hz > 0:
            self.create_timer(0.25 / self.stream_hz, self.stream)

    def on_goal(self, msg):
        if msg.header.frame_id != self.fixed:
            self.get_logger().error(f"goal in {msg.header.frame_id!r}, expected {self.fixed!r}")
            return
        T_goal = pose_matrix(msg.pose)
        if self.use_tf:  # the body moves in odom
            T_goal = np.linalg.inv(self.T_map_odom) @ T_goal
        target = T_goal @ np.linalg.inv(self.T_base_camera)
        goal_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.motion = (self.body.copy(), target, time.monotonic(), goal_ns)
        self.settled = 0

    def body_at(self, monotonic):
        """The body's pose at a time of the monotonic clock (the drive under way)."""
        if self.motion is None:
            return self.body
        start, target, t0, _ = self.motion
        u = min(1.0, max(0.0, (monotonic - t0) / self.move_s))
        return target if u >= 1.0 else blend(start, target, u)

    def tick(self):
        if self.motion is not None:
            _, _, t0, _ = self.motion
            self.body = self.body_at(time.monotonic())
            if time.monotonic() - t0 >= self.move_s:
                self.settled += 1
        now = self.get_clock().now()
        if self.use_tf:
            self.tf.publish(
                TFMessage(transforms=[transform("odom", "base_link", self.body, now.nanoseconds)])
            )
        else:
            odometry = Odometry()
            odometry.header.frame_id, odometry.child_frame_id = "odom", "base_link"
            odometry.header.stamp = now.to_msg()
            p, q = odometry.pose.pose.position, odometry.pose.pose.orientation
            p.x, p.y, p.z = map(float, self.body[:3, 3])
            q.x, q.y, q.z, q.w = map(float, quaternion(self.body[:3, :3]))
            self.pubs[ODOM].publish(odometry)
        if self.motion is not None and self.settled > SETTLE_TICKS and self.read():
            if self.stream_hz > 0:  # the first streamed frame from here on is the capture
                if self.settled_ns is None:
                    self.settled_ns = now.nanoseconds
                return
            self.capture(self.motion[3])
            self.motion = None

    def tick_map(self):
        now = self.get_clock().now().nanoseconds
        self.tf.publish(TFMessage(transforms=[transform("map", "odom", self.T_map_odom, now)]))

    def stream(self):
        """One frame of the stream at the body's pose now, moving or not (from the first goal on:
        the robot is placed in the scene then)."""
        if self.stream_ns == 0 and self.motion is None:
            return
        if not self.read():
            return
        self.stream_ns = 1
        now_ns, now_mono = self.get_clock().now().nanoseconds, time.monotonic()
        if self.slot is None:
            self.slot = (now_ns, now_mono, -1)
        t0_ns, t0_mono, last = self.slot
        period = 1.0 / self.stream_hz
        k = int((now_mono - t0_mono) / period)
        if k <= last:
            return
        self.frames_late += k - last - 1
        self._late_pending += k - last - 1
        self.slot = (t0_ns, t0_mono, k)
        ns = self.publish_frame(
            t0_ns + int(round(k * period * 1e9)), self.body_at(t0_mono + k * period)
        )
        if self.settled_ns is not None and ns > self.settled_ns and self.motion is not None:
            self.captured.publish(String(data=json.dumps({"stamp_ns": ns, "goal": self.motion[3]})))
            self.motion, self.settled_ns = None, None

    def publish_frame(self, ns=None, body=None):
        """Render at the body's pose (`body`: at the frame's exposure), publish colour, depth and
        camera info (each lost with probability `loss`) stamped `ns` (default: now); the
        frame's stamp."""
        body = self.body if body is None else body
        # the scene is the world: map with tf (localisation is right), odom without
        T_world_body = self.T_map_odom @ body if self.use_tf else body
        bgr, depth_mm = self.camera.render(T_world_body @ self.T_base_camera)
        if ns is None:
            ns = self.get_clock().now().nanoseconds  # the capture: not an odometry stamp
        for topic, msg in (
            (INFO, self.camera.info(ns)),
            (DEPTH, image(depth_mm, "16UC1", ns)),
            (COLOR, image(bgr, "bgr8", ns)),
        ):
            if self.loss > 0 and self.rng.random() < self.loss:
                self.parts_lost += 1
                continue
            self.pubs[topic].publish(msg)
            if topic == COLOR:
                self._count_late(ns)
        self.frames_published += 1
        return ns

    def _count_late(self, color_ns: int) -> None:
        """A colour image went out at `color_ns`: the late slots since the previous one count as
        short when the gap between the two is at most SHORT_STALL_S."""
        last, self._last_color_ns = self._last_color_ns, color_ns
        if last is not None and color_ns - last <= SHORT_STALL_S * 1e9:
            self.frames_late_short += self._late_pending
        self._late_pending = 0

    def read(self):
        """Every topic has had its readers for a second (a best-effort frame published before
        is lost, and a frame needs the odometry from before its stamp)."""
        if not all(self.pubs[t].get_subscription_count() >= n for t, n in self.readers.items()):
            self.read_since = None
            return False
        if self.read_since is None:
            self.read_since = time.monotonic()
        return time.monotonic() - self.read_since >= READERS_FOR_S

    def capture(self, goal_ns):
        ns = self.publish_frame()
        self.captured.publish(String(data=json.dumps({"stamp_ns": ns, "goal": goal_ns})))


_STOP: list[int] = []  # the signals received


def _stop(signum, _frame):
    # only noted: the loop in main ends after the callback in progress. Raising here (as Ctrl-C
    # does) landed once in a finaliser rclpy runs (a traceback: "Exception ignored in ... Future
    # .__del__"), and shutting the context down from here let a tick interrupted mid-way
    # publish on a dead context
    _STOP.append(signum)


def main(config):
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _stop)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = Driver(config)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while not _STOP:
            executor.spin_once(timeout_sec=0.1)
    finally:
        # what it sent, for the bench (stdout)
        print(
            json.dumps(
                {
                    "frames_published": node.frames_published,
                    "parts_lost": node.parts_lost,
                    "frames_late": node.frames_late,
                    "frames_late_short": node.frames_late_short,
                }
            ),
            flush=True,
        )
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main(json.loads(sys.argv[1]))
