"""A synthetic object-level scene (coloured sphere and box) with a ray-cast RGB-D camera.

It has the fields of a sim_bridge Scene, so evaluation, benchmarks and tests run on a known
geometry without the simulator; `make_run` writes a run directory from it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from area3d_eval.render import MeshRenderer
from area3d_eval.rundir import write_episode, write_frame
from area3d_msgs_py.camera import PAPER_HFOV_DEG, PAPER_MAX_RANGE, intrinsics
from area3d_msgs_py.camera_pose import look_at


def hemisphere_views(
    center: np.ndarray, radius: float, azimuths_deg: np.ndarray, elevations_deg: np.ndarray
) -> np.ndarray:
    """(N, 4, 4) poses on a hemisphere around `center`, all looking at it (one per azimuth/elevation pair)."""
    az, el = np.radians(azimuths_deg), np.radians(elevations_deg)
    eyes = np.asarray(center) + radius * np.stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1
    )
    return np.stack([look_at(e, center) for e in eyes])


def _coloured(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    # a smooth colour gradient plus stripes, so images have texture for PSNR / SSIM to see
    p = mesh.vertices
    stripes = 0.5 + 0.5 * np.sin(60.0 * p[:, 2])
    rgb = np.stack([0.3 + 3.0 * (p[:, 0] + 0.15), 0.3 + 3.0 * (p[:, 1] + 0.15), stripes], axis=1)
    mesh.visual.vertex_colors = (np.clip(rgb, 0.0, 1.0) * 255).astype(np.uint8)
    return mesh


@dataclass
class SyntheticScene:
    """Sphere (r = 8 cm) and box (8 cm) on the ground plane, object-level settings of the paper."""

    name: str = "synthetic_object"
    level: str = "object"
    tau: float = 0.01  # metres; the object-level F-score threshold (DESIGN.md)
    gamma: float = 0.01  # the paper's object-level global weight
    roi_min: np.ndarray = field(default_factory=lambda: np.array([-0.2, -0.2, 0.0]))
    roi_max: np.ndarray = field(default_factory=lambda: np.array([0.2, 0.2, 0.2]))
    workspace_min: np.ndarray = field(default_factory=lambda: np.array([-1.0, -1.0, 0.05]))
    workspace_max: np.ndarray = field(default_factory=lambda: np.array([1.0, 1.0, 1.0]))
    view_radius: float = 0.6  # metres from the ROI centre
    subdivisions: int = 4  # icosphere subdivisions of the sphere
    num_eval_views: int = 8  # held-out views, alternating between two elevations

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (self.roi_min + self.roi_max)

    @property
    def initial_views(self) -> np.ndarray:
        return hemisphere_views(
            self.center, self.view_radius, np.array([0.0, 90.0, 180.0, 270.0]), np.full(4, 30.0)
        )

    @property
    def eval_views(self) -> np.ndarray:
        n = self.num_eval_views
        az = np.arange(n) * 360.0 / n + 180.0 / n
        return hemisphere_views(
            self.center, self.view_radius, az, np.where(np.arange(n) % 2 == 0, 20.0, 55.0)
        )

    def planned_views(self, count: int, seed: int = 0) -> np.ndarray:
        """`count` random hemisphere views (a stand-in for a policy's choice)."""
        rng = np.random.default_rng(seed)
        return hemisphere_views(
            self.center, self.view_radius, rng.uniform(0, 360, count), rng.uniform(10, 75, count)
        )

    def ground_truth_mesh(self) -> trimesh.Trimesh:
        sphere = trimesh.creation.icosphere(subdivisions=self.subdivisions, radius=0.08)
        sphere.apply_translation([-0.06, 0.0, 0.08])
        box = trimesh.creation.box(extents=[0.08, 0.08, 0.08])
        box.apply_translation([0.09, 0.02, 0.04])
        return _coloured(trimesh.util.concatenate([sphere, box]))


class SyntheticRenderer:
    """RGB-D camera of a SyntheticScene, with the interface of sim_bridge.render.RgbdRenderer."""

    def __init__(
        self,
        scene: SyntheticScene,
        width: int = 640,
        height: int = 480,
        hfov_deg: float = PAPER_HFOV_DEG,
        max_range: float = PAPER_MAX_RANGE,
    ) -> None:
        self.width, self.height, self.max_range = int(width), int(height), float(max_range)
        self.K = intrinsics(self.width, self.height, hfov_deg)
        self._renderer = MeshRenderer(scene.ground_truth_mesh())

    def render(self, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rgb, depth = self._renderer.render(self.K, T_world_cam, self.width, self.height)
        depth[depth > self.max_range] = np.nan
        return rgb, depth

    def close(self) -> None:
        self._renderer = None


def make_run(
    run_dir: Path,
    scene: SyntheticScene,
    policy: str = "random",
    seed: int = 0,
    budget: int = 8,
    width: int = 160,
    height: int = 120,
    poses: np.ndarray | None = None,
) -> Path:
    """Write a run directory: |O_0| initial views plus `budget` planned ones (random hemisphere
    views of `seed` unless `poses` (budget, 4, 4) is given), rendered by SyntheticRenderer."""
    run_dir = Path(run_dir)
    planned = scene.planned_views(budget, seed) if poses is None else np.asarray(poses)
    all_poses = np.concatenate([scene.initial_views, planned])
    kinds = ["initial"] * len(scene.initial_views) + ["planned"] * len(planned)
    renderer = SyntheticRenderer(scene, width, height)
    rng = np.random.default_rng(seed)
    views = []
    for i, (T, kind) in enumerate(zip(all_poses, kinds, strict=True)):
        rgb, depth = renderer.render(T)
        write_frame(run_dir, i, rgb, depth, renderer.K, T, stamp_ns=(i + 1) * 10**9)
        stage = {
            "perception": float(rng.uniform(0.05, 0.1)),
            "planner": float(rng.uniform(0.1, 0.3)),
        }
        views.append(
            {
                "index": i,
                "stamp_ns": (i + 1) * 10**9,
                "T_world_cam": T,
                "kind": kind,
                "stage_times_s": stage,
            }
        )
    timings = {
        "perception": sum(v["stage_times_s"]["perception"] for v in views),
        "planner": sum(v["stage_times_s"]["planner"] for v in views),
        "render": 0.02 * len(views),
    }
    write_episode(
        run_dir,
        {
            "scene": scene.name,
            "policy": policy,
            "seed": seed,
            "budget": budget,
            "level": scene.level,
            "mode": "batch",
            "views": views,
            "timings_s": timings,
            "config": {
                "source": "area3d_eval.synthetic",
                "planner": {"roi_min": scene.roi_min.tolist(), "roi_max": scene.roi_max.tolist()},
            },
        },
    )
    return run_dir
