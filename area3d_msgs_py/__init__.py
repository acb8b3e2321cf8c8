"""ROS 2 message types, numpy codecs and the rclpy / Cyclone DDS transport.

- ``msgs``: message classes (ROS 2 Jazzy, from rosbags) and CDR ``serialize`` / ``deserialize``
- ``codecs``: Image / PointCloud2 / Pose / CameraInfo <-> numpy
- ``node``: ``Node`` and ``run_node``, on rclpy when available, else Cyclone DDS
- ``dds_config``: ``use_loopback(domain_id)`` to keep DDS traffic on 127.0.0.1
- ``errors``: ``InputError`` for bad input at a boundary
"""
