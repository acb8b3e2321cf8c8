"""A stand-in next-best-view server written only against the generated interfaces: a plain rclpy
node that imports nothing from the project, only `area3d_interfaces` and `tf2_msgs` as
`make install` builds them (or as colcon and a ROS 2 install provide them).

    python next_best_view_server.py

It serves area3d_interfaces/srv/NextBestView on `area3d/planner/select_views` with an answer
computed from the request, so that a caller can tell it crossed: `count` views (3 when 0) at
x = current x + 1, 2, ..., in the request's frame and stamp, with gains 1, 1/2, ...; a mode other
than "", "closed_loop" or "batch" is refused (success false, the reason in message). It also
publishes one TF edge (world -> camera_link) on /tf every 50 ms. Runs until SIGINT or SIGTERM.
"""

import signal

import rclpy
from area3d_interfaces.srv import NextBestView
from geometry_msgs.msg import Pose, TransformStamped
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from tf2_msgs.msg import TFMessage

MODES = ("", "closed_loop", "batch")


class NextBestViewServer(Node):
    def __init__(self) -> None:
        super().__init__("next_best_view_server")
        self.create_service(NextBestView, "area3d/planner/select_views", self.select_views)
        self.tf = self.create_publisher(TFMessage, "/tf", 10)
        self.create_timer(0.05, self.publish_tf)

    def select_views(self, request, response):
        response.views.header = request.current.header
        if request.mode not in MODES:
            response.success = False
            response.message = f"mode: got {request.mode!r}, expected closed_loop or batch"
            return response
        count = request.count or 3
        x0 = request.current.pose.position.x
        for i in range(count):
            pose = Pose()
            pose.position.x = x0 + i + 1
            response.views.poses.append(pose)
        response.gains = [1.0 / (i + 1) for i in range(count)]
        response.success = True
        return response

    def publish_tf(self) -> None:
        edge = TransformStamped()
        edge.header.stamp = self.get_clock().now().to_msg()
        edge.header.frame_id = "world"
        edge.child_frame_id = "camera_link"
        edge.transform.translation.z = 1.5
        self.tf.publish(TFMessage(transforms=[edge]))


def main() -> None:
    signal.signal(signal.SIGTERM, lambda *_: rclpy.try_shutdown())
    rclpy.init()
    node = NextBestViewServer()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
