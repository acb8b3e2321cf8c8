"""ROS 2 message types, numpy codecs and the rclpy / Cyclone DDS transport."""
