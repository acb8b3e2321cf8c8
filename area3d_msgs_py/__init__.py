"""ROS 2 message classes, numpy codecs, QoS, middleware setup and declared parameters.

- ``msgs``: the generated message classes of the ROS 2 wheels, ``serialize`` / ``deserialize``
- ``codecs``: Image / PointCloud2 / Pose / CameraInfo <-> numpy
- ``topics``: the graph's topics and service: names, types, QoS, writers and readers
- ``qos``: the graph's QoS profiles
- ``camera``: the paper's camera (field of view, range) and the pinhole intrinsics it makes
- ``depth_sensor``, ``depth_surface``: a depth camera's noise description and a depth image's
  incidence angles and edges (the simulated camera's noise and perception's confidence)
- ``rotations``: quaternions, rotation matrices, slerp, rigid transforms
- ``transforms``: ``TransformBuffer`` and ``PoseStream``, camera poses at an image's stamp
- ``camera_pose``: ``look_at`` / ``look_rotation``, camera poses in the graph's conventions
- ``middleware``: Fast DDS transport profile, graph environment, ``DomainLease``
- ``parameters``: ``Param`` and ``declare_parameters`` (typed, described, validated)
- ``param_fields``: ``described`` dataclass fields, a core's parameters documented once
- ``guard``: callbacks that log bad input instead of ending the node
- ``probe``: a node of one's own beside a graph (tests, benchmarks, scripts)
- ``errors``: ``InputError`` for bad input at a boundary
"""
