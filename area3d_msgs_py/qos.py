"""The QoS profiles of the graph's topics (reliable, keep-last), and the choice of QoS for the
camera's topics a node subscribes to (reliable, or best effort as camera drivers publish)."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from area3d_msgs_py.errors import InputError

#: ROS 2's default depth for ordinary topics.
DEFAULT_DEPTH = 10
# Frames arrive in bursts (the initial views, 15 at room level); the default depth would drop the
# oldest while a node is busy, and every captured frame matters.
FRAME_DEPTH = 50


def reliable(depth: int = DEFAULT_DEPTH) -> QoSProfile:
    """Reliable, volatile, keep-last ``depth`` (ROS 2's default profile with another depth)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def frames() -> QoSProfile:
    """Per-frame image, pose and camera-info topics."""
    return reliable(FRAME_DEPTH)


def graph_frames(depth: int = FRAME_DEPTH) -> QoSProfile:
    """Per-frame outputs one graph node computes for another (perception -> planner, semantics ->
    planner): transient-local keep-last ``depth``, on both sides. A reader that matches late (a
    node whose discovery is still running when the first frames are processed) still gets them;
    volatile readers (RViz, a recorder) match too."""
    return latched(depth)


def latched(depth: int = 1) -> QoSProfile:
    """Transient-local keep-last: a subscriber that starts late still gets the last ``depth``."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def sensor_data(depth: int = FRAME_DEPTH) -> QoSProfile:
    """Best effort, volatile, keep-last ``depth``: ROS 2's sensor-data profile (rclpy's
    ``qos_profile_sensor_data``), which camera drivers publish with. A reader's depth bounds only
    its own queue; the sensor-data profile's 5 would drop frames of a burst while a node is busy."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
    )


#: The choices of a camera-input QoS parameter. `reliable` matches reliable publishers only (our
#: simulated camera, a bag played back); `sensor_data` matches best-effort and reliable publishers
#: alike, and is what a driver publishing with the sensor-data profile needs: a reliable reader
#: never matches a best-effort writer (DDS), and nothing but an incompatible-QoS event says so.
CAMERA_QOS_CHOICES = ("reliable", "sensor_data")


def parse_camera_qos(value: object, field: str = "camera_qos") -> str:
    """A camera-input QoS choice, checked: one of CAMERA_QOS_CHOICES (InputError naming `field`)."""
    if value not in CAMERA_QOS_CHOICES:
        raise InputError(
            field,
            value,
            f"one of {', '.join(CAMERA_QOS_CHOICES)} (sensor_data for a driver that publishes "
            "best effort)",
        )
    return str(value)


def camera_input(choice: str, depth: int = FRAME_DEPTH, field: str = "camera_qos") -> QoSProfile:
    """The profile of a subscription to the camera's images, camera info or poses."""
    if parse_camera_qos(choice, field) == "sensor_data":
        return sensor_data(depth)
    return reliable(depth)
