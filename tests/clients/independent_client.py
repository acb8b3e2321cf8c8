"""An independent ROS 2 client of the AREA3D graph: a plain rclpy node written only against the
documented topic and service names (README, "The graph"); it imports nothing from the project.

    python independent_client.py '{"target": [x, y, z], "eyes": [[x, y, z], ...]}'

It drives the camera through the given views, checks every output topic (encodings, sizes,
frames, field names), calls next_best_view one view at a time (closed loop) and for several
views at once (batch), and checks that a subscriber that starts late still gets the latched
grid. Prints one JSON line with what it saw; exits 1 with the failed check otherwise.
"""

import json
import sys
import threading
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from nav_msgs.srv import GetPlan
from rclpy.executors import MultiThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import String

TIMEOUT_S = 90.0
FRAMES = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
# README: perception's and semantics' per-frame outputs are transient local on both sides
# (keep-last 50), so a reader matched after a frame's output went out still gets it.
GRAPH_FRAMES = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=50,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
LATCHED = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
TOPICS = {
    "/area3d/camera/color/image_raw": (Image, FRAMES),
    "/area3d/camera/depth/image_raw": (Image, FRAMES),
    "/area3d/camera/camera_info": (CameraInfo, FRAMES),
    "/area3d/camera/pose": (PoseStamped, FRAMES),
    "/area3d/camera/status": (String, FRAMES),
    "/area3d/perception/depth": (Image, GRAPH_FRAMES),
    "/area3d/perception/confidence": (Image, GRAPH_FRAMES),
    "/area3d/semantics/regions": (String, LATCHED),
    "/area3d/semantics/weight": (Image, GRAPH_FRAMES),
    "/area3d/semantics/uncertainty": (Image, GRAPH_FRAMES),
    "/area3d/planner/uncertainty_grid": (PointCloud2, LATCHED),
    "/area3d/planner/next_views": (Path, FRAMES),
    "/area3d/planner/status": (String, FRAMES),
}
GRID_FIELDS = ["x", "y", "z", "uncertainty", "geometric", "semantic", "occupancy", "hard"]


def check(condition, what):
    if not condition:
        raise AssertionError(what)


def stamp_ns(header):
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def look_at(eye, target):
    """Optical-frame pose (z forward, x right, y down) at `eye` looking at `target`."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    w = np.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2.0
    q = np.array(
        [
            (R[2, 1] - R[1, 2]) / (4 * w),
            (R[0, 2] - R[2, 0]) / (4 * w),
            (R[1, 0] - R[0, 1]) / (4 * w),
            w,
        ]
    )
    return eye, q / np.linalg.norm(q)


class Client:
    def __init__(self):
        self.node = rclpy.create_node("independent_client")
        self.got = {topic: [] for topic in TOPICS}
        self.subs = {}
        for topic, (msg_type, qos) in TOPICS.items():
            self.subs[topic] = self.node.create_subscription(
                msg_type, topic, self.got[topic].append, qos
            )
        self.goal = self.node.create_publisher(PoseStamped, "/area3d/camera/goal_pose", FRAMES)
        self.nbv = self.node.create_client(GetPlan, "/area3d/planner/next_best_view")
        self.executor = MultiThreadedExecutor()
        self.executor.add_node(self.node)
        # spun until a future of its own completes, which ends the wait: rclpy's
        # Executor.shutdown destroys the guard condition a spin on another thread still waits on
        self.stopping = Future()
        self.spinner = threading.Thread(
            target=self.executor.spin_until_future_complete, args=(self.stopping,), daemon=True
        )
        self.spinner.start()

    def close(self, *nodes):
        self.stopping.set_result(True)
        self.spinner.join(timeout=10)
        self.executor.shutdown()
        for node in (self.node, *nodes):
            node.destroy_node()

    @staticmethod
    def wait(predicate, what, timeout_s=TIMEOUT_S):
        deadline = time.monotonic() + timeout_s
        while not predicate():
            check(time.monotonic() < deadline, f"timed out waiting for {what}")
            time.sleep(0.02)

    def status_of(self, stamp):
        for msg in list(self.got["/area3d/camera/status"]):
            status = json.loads(msg.data)
            if status["stamp_ns"] == stamp:
                return status
        return None

    def planner_status(self):
        messages = list(self.got["/area3d/planner/status"])
        return json.loads(messages[-1].data) if messages else {}

    def capture(self, position, q):
        stamp = time.time_ns()
        msg = PoseStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        msg.header.frame_id = "world"
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, position)
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = map(float, q)
        self.goal.publish(msg)
        self.wait(lambda: self.status_of(stamp) is not None, f"camera status of goal {stamp}")
        status = self.status_of(stamp)
        check(status["ok"], f"the camera refused goal {stamp}: {status['reason']}")
        for topic in (
            "/area3d/camera/color/image_raw",
            "/area3d/camera/depth/image_raw",
            "/area3d/camera/camera_info",
            "/area3d/camera/pose",
        ):
            self.wait(
                lambda t=topic: any(stamp_ns(m.header) == stamp for m in list(self.got[t])),
                f"{topic} for {stamp}",
            )
        return stamp

    def plan(self, stamp, position, q, count):
        request = GetPlan.Request()
        request.start.header.stamp.sec, request.start.header.stamp.nanosec = divmod(
            stamp, 1_000_000_000
        )
        request.start.header.frame_id = "world"
        p, o = request.start.pose.position, request.start.pose.orientation
        p.x, p.y, p.z = map(float, position)
        o.x, o.y, o.z, o.w = map(float, q)
        request.goal.pose.position.x = float(count)
        future = self.nbv.call_async(request)
        self.wait(future.done, "the next_best_view answer", 180.0)
        plan = future.result().plan
        check(plan.header.frame_id == "world", f"plan frame {plan.header.frame_id!r}")
        views = []
        for pose in plan.poses:
            check(pose.header.frame_id == "world", "planned pose frame")
            p, o = pose.pose.position, pose.pose.orientation
            q = np.array([o.x, o.y, o.z, o.w])
            position = np.array([p.x, p.y, p.z])
            check(abs(np.linalg.norm(q) - 1.0) < 1e-3, f"unit quaternion, got {q}")
            check(np.isfinite(position).all() and np.abs(position).max() < 10.0, "finite pose")
            views.append((position, q))
        return views


def check_image(msg, encoding, width, height, frame="camera_optical_frame"):
    bytes_per_pixel = {"rgb8": 3, "32FC1": 4}[encoding]
    check(msg.encoding == encoding, f"encoding {msg.encoding!r}, expected {encoding}")
    check((msg.width, msg.height) == (width, height), f"size {msg.width}x{msg.height}")
    check(msg.step == width * bytes_per_pixel, f"step {msg.step}")
    check(len(msg.data) == msg.step * msg.height, "data length")
    check(msg.header.frame_id == frame, f"frame {msg.header.frame_id!r}")
    if encoding == "32FC1":
        return np.frombuffer(bytes(msg.data), dtype="<f4").reshape(height, width)
    return None


def main():
    spec = json.loads(sys.argv[1])
    rclpy.init()
    client = Client()
    extra = []  # nodes added to the client's executor later
    try:
        run(client, spec, extra)
    finally:
        # a failed check too stops the executor's thread before the interpreter ends (left
        # spinning, it aborted the process at exit instead of letting it exit 1)
        client.close(*extra)
        rclpy.try_shutdown()


def run(client, spec, extra):
    camera_topics = [t for t in TOPICS if t.startswith("/area3d/camera/")]
    client.wait(lambda: client.goal.get_subscription_count() >= 1, "the camera's goal subscription")
    client.wait(
        lambda: all(client.subs[t].get_publisher_count() >= 1 for t in camera_topics),
        "the camera's topics",
    )
    client.wait(lambda: client.nbv.service_is_ready(), "the next_best_view service")
    views = [look_at(eye, spec["target"]) for eye in spec["eyes"]]
    stamps = [client.capture(*view) for view in views]
    client.wait(
        lambda: client.planner_status().get("frames_fused", 0) >= len(stamps), "fused initial views"
    )

    # closed loop: one view per request, each captured before the next request
    closed = []
    for _ in range(2):
        (view,) = client.plan(stamps[-1], *views[-1], 1)
        closed.append(view)
        views.append(view)
        stamps.append(client.capture(*view))
    # batch: several views from one request
    batch = client.plan(stamps[-1], *views[-1], 3)
    check(len(batch) == 3, f"batch of 3 views, got {len(batch)}")

    info = client.got["/area3d/camera/camera_info"][-1]
    width, height = info.width, info.height
    check(info.header.frame_id == "camera_optical_frame", "camera_info frame")
    check(len(info.k) == 9 and info.k[0] > 0 and info.k[8] == 1.0, "camera_info K")
    for msg in client.got["/area3d/camera/color/image_raw"]:
        check_image(msg, "rgb8", width, height)
    for msg in client.got["/area3d/camera/depth/image_raw"]:
        check_image(msg, "32FC1", width, height)
    for msg in client.got["/area3d/camera/pose"]:
        check(msg.header.frame_id == "world", "camera pose frame")
    client.wait(
        lambda: len(client.got["/area3d/perception/confidence"]) >= len(stamps), "perception"
    )
    for msg in client.got["/area3d/perception/depth"]:
        check_image(msg, "32FC1", width, height)
    for msg in client.got["/area3d/perception/confidence"]:
        conf = check_image(msg, "32FC1", width, height)
        check(np.nanmin(conf) >= 0.0 and np.nanmax(conf) <= 1.0, "confidence in [0, 1]")
    check(
        {stamp_ns(m.header) for m in client.got["/area3d/perception/depth"]} >= set(stamps),
        "perception depth for every captured frame",
    )
    client.wait(lambda: client.got["/area3d/semantics/regions"], "semantic regions")
    regions = json.loads(client.got["/area3d/semantics/regions"][-1].data)
    check(isinstance(regions.get("images"), list) and regions["images"], "regions JSON images")
    client.wait(lambda: client.got["/area3d/semantics/uncertainty"], "semantic uncertainty")
    for msg in client.got["/area3d/semantics/weight"]:
        weight = check_image(msg, "32FC1", width, height)
        check(weight.min() >= 0.0 and weight.max() <= 1.0, "weight in [0, 1]")
    for msg in client.got["/area3d/semantics/uncertainty"]:
        check(msg.encoding == "32FC1" and msg.header.frame_id == "camera_optical_frame", "U_sem")
    grid = client.got["/area3d/planner/uncertainty_grid"][-1]
    check(grid.header.frame_id == "world", f"grid frame {grid.header.frame_id!r}")
    check(
        [f.name for f in grid.fields] == GRID_FIELDS, f"grid fields {[f.name for f in grid.fields]}"
    )
    check(all(f.datatype == PointField.FLOAT32 and f.count == 1 for f in grid.fields), "float32")
    check(grid.row_step == grid.point_step * grid.width and grid.width > 0, "grid layout")
    check(len(grid.data) == grid.row_step * grid.height, "grid data length")

    # Every answer is also published on next_views (volatile, as a plan is news): the planner's
    # writer matches this reader on its own time, so an early one can be missed, but the last
    # answer, long after the client's first messages, arrives; each one received is an answer.
    def positions(path):
        return np.array(
            [[q.pose.position.x, q.pose.position.y, q.pose.position.z] for q in path.poses]
        )

    answers = [np.array([v[0] for v in answer]) for answer in ([c] for c in closed)] + [
        np.array([v[0] for v in batch])
    ]
    client.wait(
        lambda: any(
            len(m.poses) == 3 and np.allclose(positions(m), answers[-1], atol=1e-6)
            for m in list(client.got["/area3d/planner/next_views"])
        ),
        "the batch plan on next_views",
    )
    for msg in client.got["/area3d/planner/next_views"]:
        check(msg.header.frame_id == "world", "next_views frame")
        check(
            any(
                len(msg.poses) == len(a) and np.allclose(positions(msg), a, atol=1e-6)
                for a in answers
            ),
            "next_views: each message is one of the answers",
        )
    check("frames_fused" in client.planner_status(), "planner status JSON")

    # a subscriber that starts now still gets the latched grid
    late_grid = []
    late = rclpy.create_node("late_subscriber")
    extra.append(late)
    late.create_subscription(
        PointCloud2, "/area3d/planner/uncertainty_grid", late_grid.append, LATCHED
    )
    client.executor.add_node(late)
    client.wait(lambda: late_grid, "the latched grid for a late subscriber", 30.0)
    check([f.name for f in late_grid[0].fields] == GRID_FIELDS, "late grid fields")

    print(
        json.dumps(
            {
                "captured": len(stamps),
                "closed_loop_views": [v[0].tolist() for v in closed],
                "batch_views": [v[0].tolist() for v in batch],
                "grid_points": late_grid[0].width,
                "counts": {t: len(m) for t, m in client.got.items()},
            }
        ),
        flush=True,
    )


if __name__ == "__main__":
    try:
        main()
    except AssertionError as err:
        print(f"CHECK FAILED: {err}", flush=True)
        sys.exit(1)
