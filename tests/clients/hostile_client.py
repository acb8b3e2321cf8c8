"""A hostile (or merely broken) ROS 2 publisher: a plain rclpy node that feeds every topic the
AREA3D nodes subscribe to with malformed messages. It imports nothing from the project and knows
only the documented topic names and types (README, "The graph").

    python hostile_client.py '{"width": 160, "height": 120, "readers": {"/area3d/camera/pose": 2}}'

It waits until each topic has the given number of readers, publishes every case once, waits for
the last one to be acknowledged and prints one JSON line: the cases it sent, each with its topic,
its name and the field a node should name when it rejects it.

With `"poses": true` it feeds the camera pose's other sources instead, for nodes that take it
from TF (`pose_source: tf`, world frame `world`) or odometry (`pose_source: odometry`, world frame
`odom`, body `base_link`, jumps checked): bad transforms on /tf and /tf_static and bad odometry on
/area3d/odom (each rejected by field), and whole frames whose pose is late or never comes (each
dropped by cause: `"drops"` in the JSON line says which node drops which).
"""

import json
import sys
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage

TIMEOUT_S = 180.0  # generous: every wait ends once its condition holds
VOLATILE = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
# perception's and semantics' outputs are read transient local: a writer must offer it to match
TRANSIENT = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
COLOR = "/area3d/camera/color/image_raw"
DEPTH = "/area3d/camera/depth/image_raw"
INFO = "/area3d/camera/camera_info"
POSE = "/area3d/camera/pose"
GOAL = "/area3d/camera/goal_pose"
P_DEPTH = "/area3d/perception/depth"
P_CONF = "/area3d/perception/confidence"
S_USEM = "/area3d/semantics/uncertainty"
S_REQUEST = "/area3d/semantics/request"
TF = "/tf"
TF_STATIC = "/tf_static"
ODOM = "/area3d/odom"
TOPICS = {
    COLOR: (Image, VOLATILE),
    DEPTH: (Image, VOLATILE),
    INFO: (CameraInfo, VOLATILE),
    POSE: (PoseStamped, VOLATILE),
    GOAL: (PoseStamped, VOLATILE),
    P_DEPTH: (Image, TRANSIENT),
    P_CONF: (Image, TRANSIENT),
    S_USEM: (Image, TRANSIENT),
    S_REQUEST: (String, VOLATILE),
    TF: (TFMessage, VOLATILE),
    TF_STATIC: (TFMessage, TRANSIENT),
    ODOM: (Odometry, VOLATILE),
}
YEAR_NS = 365 * 24 * 3600 * 1_000_000_000
HUGE = 8192  # an 8k x 8k rgb8 image: 201 MB


def set_stamp(header, ns, frame_id):
    header.stamp.sec, header.stamp.nanosec = divmod(int(ns), 1_000_000_000)
    header.frame_id = frame_id


def image(ns, array, encoding, frame_id="camera_optical_frame"):
    msg = Image()
    set_stamp(msg.header, ns, frame_id)
    msg.height, msg.width = array.shape[:2]
    msg.encoding = encoding
    msg.step = array.shape[1] * array.itemsize * (array.shape[2] if array.ndim == 3 else 1)
    msg.data = np.ascontiguousarray(array).tobytes()
    return msg


def pose(ns, q=(0.0, 0.0, 0.0, 1.0), p=(0.0, -0.7, 0.4), frame_id="world"):
    msg = PoseStamped()
    set_stamp(msg.header, ns, frame_id)
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, p)
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = map(float, q)
    return msg


def camera_info(ns, width, height, fx=80.0):
    msg = CameraInfo()
    set_stamp(msg.header, ns, "camera_optical_frame")
    msg.width, msg.height = width, height
    msg.k = [fx, 0.0, width / 2, 0.0, fx, height / 2, 0.0, 0.0, 1.0]
    return msg


def cases(now, w, h):
    """(topic, case, message, field a node names when it rejects it) for every malformed input."""
    rgb = np.full((h, w, 3), 128, np.uint8)
    depth = np.full((h, w), 0.6, np.float32)
    conf = np.full((h, w), 0.5, np.float32)
    future, before_epoch = now + YEAR_NS, -YEAR_NS

    def broken_step(msg):
        msg.step = 3
        return msg

    def short_data(msg):
        msg.data = bytes(msg.data)[: len(msg.data) // 2]
        return msg

    def with_value(array, value):
        bad = array.copy()
        bad[: h // 4] = value
        return bad

    yield from (
        (COLOR, "wrong encoding (yuv422)", image(now, rgb[..., :2].copy(), "yuv422"), "encoding"),
        (COLOR, "depth image on the color topic", image(now, depth, "32FC1"), "encoding"),
        (COLOR, "step smaller than a row", broken_step(image(now, rgb, "rgb8")), "step"),
        (COLOR, "data shorter than height x step", short_data(image(now, rgb, "rgb8")), "data"),
        (COLOR, "zero-size image", image(now, rgb[:0, :0], "rgb8"), "width x height"),
        (COLOR, "8k x 8k image", image(now, np.zeros((HUGE, HUGE, 3), np.uint8), "rgb8"), "width x height"),
        (COLOR, "stamp a year ahead", image(future, rgb, "rgb8"), "header.stamp"),
        (COLOR, "stamp before 1970", image(before_epoch, rgb, "rgb8"), "header.stamp"),
        (COLOR, "empty frame_id", image(now, rgb, "rgb8", frame_id=""), "header.frame_id"),
        (DEPTH, "color image on the depth topic", image(now, rgb, "rgb8"), "encoding"),
        (DEPTH, "step smaller than a row", broken_step(image(now, depth, "32FC1")), "step"),
        (DEPTH, "zero-size image", image(now, depth[:0, :0], "32FC1"), "width x height"),
        (DEPTH, "millimetres as 32FC1", image(now, depth * np.float32(1000), "32FC1"), "data"),
        (DEPTH, "stamp a year ahead", image(future, depth, "32FC1"), "header.stamp"),
        (INFO, "fx = 0 (uncalibrated)", camera_info(now, w, h, fx=0.0), "k"),
        (INFO, "NaN in K", camera_info(now, w, h, fx=float("nan")), "k"),
        (INFO, "zero-size camera", camera_info(now, 0, 0), "width/height"),
        (INFO, "100k x 100k camera", camera_info(now, 100_000, 100_000), "width x height"),
        (INFO, "stamp a year ahead", camera_info(future, w, h), "header.stamp"),
        (POSE, "non-unit quaternion (norm 2)", pose(now, q=(0.0, 0.0, 0.0, 2.0)), "orientation"),
        (POSE, "zero quaternion", pose(now, q=(0.0, 0.0, 0.0, 0.0)), "orientation"),
        (POSE, "NaN position", pose(now, p=(float("nan"), 0.0, 0.0)), "position"),
        (POSE, "inf in quaternion", pose(now, q=(float("inf"), 0.0, 0.0, 1.0)), "orientation"),
        (POSE, "frame_id 'map' instead of 'world'", pose(now, frame_id="map"), "header.frame_id"),
        (POSE, "stamp a year ahead", pose(future), "header.stamp"),
        (GOAL, "non-unit quaternion (norm 2)", pose(now, q=(0.0, 0.0, 0.0, 2.0)), "orientation"),
        (GOAL, "NaN position", pose(now, p=(float("nan"), 0.0, 0.0)), "position"),
        (GOAL, "frame_id 'map' instead of 'world'", pose(now, frame_id="map"), "header.frame_id"),
        (P_DEPTH, "color image on a depth topic", image(now, rgb, "rgb8"), "encoding"),
        (P_DEPTH, "-inf depth", image(now, with_value(depth, -np.inf), "32FC1"), "depth"),
        (P_DEPTH, "negative depth", image(now, with_value(depth, -1.0), "32FC1"), "depth"),
        (P_DEPTH, "data shorter than height x step", short_data(image(now, depth, "32FC1")), "data"),
        (P_DEPTH, "stamp a year ahead", image(future, depth, "32FC1"), "header.stamp"),
        (P_CONF, "confidence 5", image(now, with_value(conf, 5.0), "32FC1"), "confidence"),
        (P_CONF, "-inf confidence", image(now, with_value(conf, -np.inf), "32FC1"), "confidence"),
        (P_CONF, "mono8 confidence", image(now, np.zeros((h, w), np.uint8), "mono8"), "encoding"),
        (P_CONF, "zero-size image", image(now, conf[:0, :0], "32FC1"), "width x height"),
        (S_USEM, "U_sem -1", image(now, with_value(conf, -1.0), "32FC1"), "semantic uncertainty"),
        (S_USEM, "+inf U_sem", image(now, with_value(conf, np.inf), "32FC1"), "semantic uncertainty"),
        (S_USEM, "empty frame_id", image(now, conf, "32FC1", frame_id=""), "header.frame_id"),
    )  # fmt: skip


def edge(ns, parent="world", child="camera_link", t=(0.0, -0.7, 0.4), q=(0.0, 0.0, 0.0, 1.0)):
    msg = TransformStamped()
    set_stamp(msg.header, ns, parent)
    msg.child_frame_id = child
    tr, rot = msg.transform.translation, msg.transform.rotation
    tr.x, tr.y, tr.z = map(float, t)
    rot.x, rot.y, rot.z, rot.w = map(float, q)
    return msg


def odometry(ns, p=(0.0, -0.7, 0.4), q=(0.0, 0.0, 0.0, 1.0), frame_id="odom", child="base_link"):
    msg = Odometry()
    set_stamp(msg.header, ns, frame_id)
    msg.child_frame_id = child
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = map(float, p)
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = map(float, q)
    return msg


# camera_link -> its optical frame (z forward, x right, y down)
OPTICAL_Q = (-0.5, 0.5, -0.5, 0.5)


def pose_cases(now, w, h):
    """(topic, case, message, field) for the pose sources: each valid message first (not a case:
    field None), then the malformed ones, in the order they are sent."""
    rgb = np.full((h, w, 3), 128, np.uint8)
    depth = np.full((h, w), 0.6, np.float32)
    conf = np.full((h, w), 0.5, np.float32)
    t0 = now - 1_000_000_000  # the valid samples: a second ago, 10 ms apart
    t1 = t0 + 10_000_000
    later = t1 + 10_000_000
    future = now + YEAR_NS
    static = TFMessage(
        transforms=[edge(t0, "camera_link", "camera_optical_frame", (0, 0, 0), OPTICAL_Q)]
    )
    two = TFMessage(transforms=[edge(later), edge(later, "world", "other", q=(0.0, 0.0, 2.0, 0.0))])
    yield from (
        (TF_STATIC, "the camera's mount", static, None),
        (TF, "world -> camera_link", TFMessage(transforms=[edge(t0)]), None),
        (TF, "world -> camera_link, 10 ms later", TFMessage(transforms=[edge(t1)]), None),
        (TF, "non-unit quaternion (norm 2)", TFMessage(transforms=[edge(later, q=(0, 0, 0, 2.0))]), "transforms[0].transform.rotation"),
        (TF, "NaN translation", TFMessage(transforms=[edge(later, t=(float("nan"), 0, 0))]), "transforms[0].transform.translation"),
        (TF, "a jump: 50 m in 10 ms", TFMessage(transforms=[edge(later, t=(50.0, 0, 0.4))]), "transforms[0].transform.translation"),
        (TF, "stamp a year ahead", TFMessage(transforms=[edge(future)]), "transforms[0].header.stamp"),
        (TF, "a second parent for camera_link", TFMessage(transforms=[edge(later, parent="map")]), "transforms[0].header.frame_id"),
        (TF, "a frame its own parent", TFMessage(transforms=[edge(later, "world", "world")]), "transforms[0].child_frame_id"),
        (TF, "the second transform of a message bad", two, "transforms[1].transform.rotation"),
        (TF_STATIC, "zero quaternion", TFMessage(transforms=[edge(t0, "camera_link", "lens", q=(0, 0, 0, 0))]), "transforms[0].transform.rotation"),
        (ODOM, "odometry", odometry(t0), None),
        (ODOM, "odometry, 10 ms later", odometry(t1), None),
        (ODOM, "non-unit quaternion (norm 2)", odometry(later, q=(0, 0, 0, 2.0)), "pose.pose.orientation"),
        (ODOM, "NaN position", odometry(later, p=(float("nan"), 0, 0)), "pose.pose.position"),
        (ODOM, "a jump: 50 m in 10 ms", odometry(later, p=(50.0, 0, 0.4)), "pose.pose.position"),
        (ODOM, "stamp a year ahead", odometry(future), "header.stamp"),
        (ODOM, "frame_id 'map' instead of 'odom'", odometry(later, frame_id="map"), "header.frame_id"),
        (ODOM, "child_frame_id of another body", odometry(later, child="arm_link"), "child_frame_id"),
        # whole frames whose pose never comes: after every transform (late), of an unknown frame
        (INFO, "camera info", camera_info(now, w, h), None),
        (COLOR, "a frame after the last transform", image(now, rgb, "rgb8"), None),
        (DEPTH, "... its depth", image(now, depth, "32FC1"), None),
        (COLOR, "a frame in a frame no transform names", image(now, rgb, "rgb8", "nowhere"), None),
        (DEPTH, "... its depth", image(now, depth, "32FC1", "nowhere"), None),
        (P_DEPTH, "perception's depth after the last odometry", image(now, depth, "32FC1"), None),
        (P_CONF, "... its confidence", image(now, conf, "32FC1"), None),
    )  # fmt: skip


#: node -> {cause: frames} the pose cases make a node drop (pose_source tf / odometry)
POSE_DROPS = {"perception": {"in_future": 1, "no_transform": 1}, "planner": {"in_future": 1}}


def _acked(pub, topic: str) -> None:
    """Every reader has acknowledged every sample of `pub`, or this process fails saying so (a
    sample still unacknowledged would vanish with the writer, and the test would then see a
    count that differs for no reason it could tell)."""
    if not pub.wait_for_all_acked(rclpy.duration.Duration(seconds=TIMEOUT_S)):
        raise SystemExit(f"{topic}: not every reader acknowledged every sample in {TIMEOUT_S} s")


def main(config):
    rclpy.init()
    node = rclpy.create_node("hostile_client")
    pubs = {t: node.create_publisher(m, t, q) for t, (m, q) in TOPICS.items()}
    deadline = time.monotonic() + TIMEOUT_S
    for topic, count in config.get("readers", {}).items():
        while pubs[topic].get_subscription_count() < count:
            if time.monotonic() > deadline:
                raise SystemExit(f"timed out waiting for {count} readers on {topic}")
            time.sleep(0.02)
    now = time.time_ns()
    sent = []
    poses = config.get("poses", False)
    for topic, case, msg, field in (pose_cases if poses else cases)(
        now, config["width"], config["height"]
    ):
        if topic in config.get("readers", {}):
            pubs[topic].publish(msg)
            if field is not None:
                sent.append({"topic": topic, "case": case, "field": field})
            if poses:  # in order: each transform before the next (they come on three topics)
                _acked(pubs[topic], topic)
    # a 1 MB re-query request is well formed (any text re-queries): sent, not counted as rejected
    if S_REQUEST in config.get("readers", {}):
        pubs[S_REQUEST].publish(String(data="x" * 1_000_000))
    for topic, pub in pubs.items():  # every reader has every sample before this process goes
        _acked(pub, topic)
    print(json.dumps({"sent": sent, "drops": POSE_DROPS if poses else {}}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main(json.loads(sys.argv[1]))
