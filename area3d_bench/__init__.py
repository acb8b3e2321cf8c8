"""Benchmarks of AREA3D, behind `area3d bench NAME` (`cli.py`). They use the product packages as a
user does; no product package imports them.

- ``transport``: topics (``topic_latency``) and the next-best-view services (``planner_service``)
  between two processes
- ``tf``: a camera pose per frame from a robot's TF tree or from odometry
- ``render``: the simulated RGB-D camera's frames per second
- ``perception``, ``stereo``: the perception node's frame; the stereo backend's time and error
- ``semantics``: parse + weight maps + U_sem of a room-level query
- ``planner``, ``closed_loop``: visibility cache, lazy vs plain greedy, the closed-loop step
- ``evaluation``: the evaluation path on a synthetic episode (`area3d bench eval`)
- ``foxglove``: what the live view costs
- ``soak``, ``soak_manager``: a 10-minute RGB-D stream through perception and the planner
- ``episode``, ``episode_task``, ``episode_cluster``: every policy on every scene, in one process
  or on Dask workers
- ``frames``: scene views rendered once, so rendering does not compete with what is measured
"""
