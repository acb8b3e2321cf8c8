"""One episode with the graph's cores called in one process, in the graph's order, no transport.

The parameters are those `area3d run` gives the nodes (`presets.episode_specs`), filled in as
each node declares them (`parameter_values`), and each core is built by the function its node
builds it with (`camera_from_parameters`, `estimator_from_parameters`, `backend_from_parameters`,
`config_from_parameters`): the camera, perception estimator, semantics analysis and planner
server of the graph, fed frame by frame in closed loop. So the views chosen are those of
`area3d run` with the same scene, preset and seed (the nodes add transport and timing, not
decisions; a test compares both). Used by `area3d bench episode --in-process` to compare
policies over many scenes and seeds on a small machine; its run directories have the layout of
`area3d run` and are evaluated the same way.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from area3d_bringup.presets import episode_specs
from area3d_eval.rundir import check_depth_source, stopped_early, write_episode, write_frame
from area3d_msgs_py import codecs


def _node_values(specs: list, name: str, module: Any) -> dict:
    """The parameter values node `name` starts with: its spec's, defaults for the rest."""
    from area3d_msgs_py.parameters import parameter_values

    given = next(spec.parameters for spec in specs if spec.name == name)
    return parameter_values(module.PARAMS, given)


class _Graph:
    """The four nodes' cores, built from the episode's parameters as the nodes build them."""

    def __init__(self, specs: list) -> None:
        import area3d_perception.node as perception_node
        import area3d_planner.node as planner_node
        import area3d_semantics.node as semantics_node
        import sim_bridge.node as sim_node
        from area3d_planner.server import NextBestViewServer
        from sim_bridge.scenes import load_scene

        camera = _node_values(specs, "sim_bridge", sim_node)
        self.camera = sim_node.camera_from_parameters(load_scene(camera["scene"]), camera)
        perception = _node_values(specs, "perception", perception_node)
        self.estimator = perception_node.estimator_from_parameters(perception)
        self.stereo = perception["backend"] == "stereo"
        semantics = _node_values(specs, "semantics", semantics_node)
        self.backend, _ = semantics_node.backend_from_parameters(semantics)
        self.semantic_params = semantics_node.semantic_params(semantics)
        self.num_initial_views = semantics["num_initial_views"]
        self.fallback = semantics["fallback"]
        self.sigma_by_confidence = semantics["sigma_source"] == "confidence"
        planner = _node_values(specs, "planner", planner_node)
        self.planner_config = planner_node.config_from_parameters(planner)
        self.server = NextBestViewServer(self.planner_config)

    def close(self) -> None:
        self.camera.close()


def run_inprocess_episode(
    scene_name: str,
    policy: str,
    seed: int,
    out_dir: Path,
    budget: int | None = None,
    overrides: dict[str, dict] | None = None,
    run_name: str | None = None,
    depth_source: str = "sensor",
) -> Path:
    """Run one closed-loop episode in this process; returns its run directory (frames and
    episode.json, as `area3d run` writes them, with a timing per stage). depth_source: what the
    TSDF of the evaluation integrates (rundir.DEPTH_SOURCES); "estimated" keeps perception's depth
    and confidence in every frame file."""
    from area3d_bringup.episode_config import episode_budget
    from sim_bridge.scenes import load_scene, scene_reference

    check_depth_source(depth_source)
    scene = load_scene(scene_name)
    total = episode_budget(scene, budget)
    specs = episode_specs(scene_name, policy, seed, total, "closed_loop", overrides)
    run_dir = Path(out_dir) / (run_name or f"{scene.name}_{policy}_s{seed}")
    run_dir.mkdir(parents=True, exist_ok=True)
    graph = _Graph(specs)
    episode = _Episode(graph, run_dir, depth_source)
    try:
        for T in scene.initial_views:
            if not episode.take(T, "initial"):
                raise ValueError(f"the camera refused an initial view of {scene.name}")
        refused, stopped = 0, ""
        while len(episode.views) < total and refused <= total:
            t = time.perf_counter()
            last = episode.views[-1]
            poses, reason = graph.server.plan(
                _plan_request(np.asarray(last["T_world_cam"]), last["stamp_ns"])
            )
            episode.add_time("planning", time.perf_counter() - t)
            if not poses:  # as the graph's runner: stop early, and say why
                stopped = stopped_early(total - len(episode.views), reason)
                break
            if not episode.take(poses[0], "planned"):
                refused += 1
    finally:
        graph.close()
    write_episode(
        run_dir,
        {
            "scene": scene_reference(scene),
            "policy": policy,
            "seed": seed,
            "budget": total,
            "level": scene.level,
            "mode": "closed_loop",
            "depth_source": depth_source,
            "views": episode.views,
            "stopped_early": stopped,  # empty when the budget was spent
            "semantics": episode.semantics,
            "timings_s": episode.timings,
            "config": {spec.name: spec.parameters for spec in specs} | {"in_process": True},
        },
    )
    return run_dir


def _plan_request(T_world_cam: np.ndarray, stamp_ns: int) -> Any:
    from area3d_planner.requests import PlanRequest

    return PlanRequest(T_world_cam, stamp_ns, 1)


class _Episode:
    """Captures, perceives and fuses views as the graph does, and writes the run directory."""

    def __init__(self, graph: _Graph, run_dir: Path, depth_source: str) -> None:
        self.graph = graph
        self.run_dir = run_dir
        self.depth_source = depth_source
        self.views: list[dict] = []
        self.timings: dict[str, float] = {}
        self.captured: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
        self.analysed = False
        self.semantics: dict = {}  # as the mission manager keeps it (`SEMANTICS_KEYS`)

    def add_time(self, stage: str, seconds: float) -> None:
        self.timings[stage] = self.timings.get(stage, 0.0) + seconds

    def take(self, T: np.ndarray, kind: str) -> bool:
        """Capture at `T`, estimate, fuse; once the initial views are in, the one semantic
        query. False if the camera refused the pose."""
        graph = self.graph
        camera = graph.camera
        t = time.perf_counter()
        # the pose as the graph's goal message carries it (a quaternion): the camera renders at
        # the same pose to the last bit, and near ties between views fall alike on both paths
        cap = camera.capture(codecs.pose_to_matrix(codecs.matrix_to_pose(T)))
        self.add_time("capture", time.perf_counter() - t)
        if not cap.ok:
            return False
        stamp = (len(self.views) + 1) * 1_000_000_000
        t = time.perf_counter()
        baseline = camera.stereo_baseline if graph.stereo else None
        result = graph.estimator.process(
            cap.rgb, cap.depth, camera.K, cap.T_world_cam, right=cap.rgb_right, baseline=baseline
        )
        self.add_time("perception", time.perf_counter() - t)
        t = time.perf_counter()
        graph.server.add_frame(stamp, result.depth, result.confidence, camera.K, cap.T_world_cam)
        self.add_time("fusion", time.perf_counter() - t)
        estimates = {}
        if self.depth_source == "estimated":
            estimates = {
                "estimated_depth": result.depth,
                "confidence": result.confidence,
                "weight": result.weight,
            }
        write_frame(
            self.run_dir,
            len(self.views),
            cap.rgb,
            cap.depth,
            camera.K,
            cap.T_world_cam,
            stamp,
            **estimates,
        )
        self.views.append(
            {
                "index": len(self.views),
                "stamp_ns": stamp,
                "T_world_cam": cap.T_world_cam,
                "kind": kind,
            }
        )
        self.captured.append((stamp, cap.rgb, cap.depth, result.confidence))
        if not self.analysed and len(self.captured) == graph.num_initial_views:
            self._analyse()
        return True

    def _analyse(self) -> None:
        """The semantics node's one query with the initial views: regions, a weight map and U_sem
        per view, fused by the planner (as the node publishes them, whatever the regions)."""
        from area3d_semantics.analysis import analyze_views
        from area3d_semantics.weights import frame_uncertainty, weight_map

        graph = self.graph
        t = time.perf_counter()
        analysis = analyze_views(
            graph.backend,
            [c[1] for c in self.captured],
            [c[2] for c in self.captured],
            fallback=graph.fallback,
        )
        self.semantics = {
            "backend": analysis.backend,
            "fallback_used": analysis.fallback_used,
            "error": analysis.error,
        }
        params = graph.semantic_params
        for i, (stamp, rgb, _, confidence) in enumerate(self.captured):
            weight = weight_map(analysis.regions_of(i), rgb.shape[0], rgb.shape[1], params)
            sigma_confidence = confidence if graph.sigma_by_confidence else None
            graph.server.add_semantic(
                stamp, frame_uncertainty(weight, params.lam, sigma_confidence)
            )
        self.analysed = True
        self.add_time("semantics", time.perf_counter() - t)
