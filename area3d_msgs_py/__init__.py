"""ROS 2 message classes, numpy codecs, QoS, middleware setup and declared parameters.

- ``msgs``: the generated message classes of the ROS 2 wheels, ``serialize`` / ``deserialize``
- ``codecs``: Image / PointCloud2 / Pose / CameraInfo <-> numpy
- ``qos``: the graph's QoS profiles
- ``middleware``: Fast DDS transport profile, graph environment, ``DomainLease``
- ``parameters``: ``Param`` and ``declare_parameters`` (typed, described, validated)
- ``guard``: callbacks that log bad input instead of ending the node
- ``probe``: a node of one's own beside a graph (tests, benchmarks, scripts)
- ``errors``: ``InputError`` for bad input at a boundary
"""
