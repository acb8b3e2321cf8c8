"""Run presets: what each `--policy` name of `area3d run` sets in the graph's parameters, and the
parameters of one episode (shared by `area3d run` and the in-process path, so both decide alike).

A preset is not a planner policy (`area3d_planner.policies`): it names a configuration of the
whole graph. The paper's ablations are configurations: `no_vlm` switches the semantics off and
the planner's semantic weight to 0, `no_ff` makes the planner take every confidence as 1,
`gamma0` removes the planner's global initial weight (gamma and the weight of unobserved voxels).
`paper` is the published method as written, element by element.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from area3d_bringup.graph import GRAPH_NODES
from area3d_bringup.launch_description import NodeSpec, build_graph, load_parameters, merge

# A voxel seen over this many pixels counts whole: any voxel a view sees, as the paper's ray-cast
# masks count it (the least the parameter takes above 0, which means the level's).
PAPER_PIXELS_PER_VOXEL = 1e-6

#: preset name -> parameter overrides {node: {param: value}}
RUN_PRESETS: dict[str, dict[str, dict]] = {
    "area3d": {"planner": {"policy": "area3d"}},
    "random": {"planner": {"policy": "random"}, "semantics": {"backend": "none"}},
    "uniform": {"planner": {"policy": "uniform"}, "semantics": {"backend": "none"}},
    "vlm_naive": {"planner": {"policy": "vlm_naive"}},
    "volumetric_ig": {"planner": {"policy": "volumetric_ig"}, "semantics": {"backend": "none"}},
    "no_vlm": {
        "planner": {"policy": "area3d", "semantic_weight": 0.0},
        "semantics": {"backend": "none"},
    },
    # no feed-forward confidence in planning: the planner takes confidence 1 on whatever depth
    # the perception backend estimates (with rgbd: what the `uniform` backend gives) and U_sem's
    # sigma is constant; perception's output and the reconstruction from it stay those of every
    # other policy
    "no_ff": {
        "planner": {"policy": "area3d", "uniform_confidence": True},
        "semantics": {"sigma_source": "constant"},
    },
    # no global initial weight: nothing on the voxels no frame has covered (the planner's
    # unobserved_uncertainty) and no gamma on any voxel (planner README, "The ablations")
    "gamma0": {"planner": {"policy": "area3d", "gamma": 0.0, "unobserved_uncertainty": 0.0}},
    # the published method as written (planner README, "The paper, element by element"): U_geo =
    # 1 - mean confidence, a voxel no view covered carries gamma only, a view scores the fused
    # uncertainty under its visibility mask (every visible voxel counts whole: no achievability,
    # range, direction or resolution term) and every view is the greedy's, however small its gain
    # (no coverage views); `--mode batch` plans every view from O_0 as the paper does. Candidate
    # positions and the orientation fan stay the project's.
    "paper": {
        "planner": {
            "policy": "area3d",
            "geometric_rule": "mean",
            "unobserved_uncertainty": 0.0,
            "gain_rule": "held",
            "range_profile": False,
            "repeat_gain": 1.0,
            "pixels_per_voxel": PAPER_PIXELS_PER_VOXEL,
            "coverage_below": 0.0,
        }
    },
}


def _camera(min_range: float, max_range: float, focal_px: float, **noise: float) -> dict:
    """The parameters of a camera class, the same in every node that describes the camera: the
    simulated camera's noise and range, perception's sensor model, the planner's limits."""
    sensor = {"sensor.min_range": min_range, "sensor.reference_focal_px": focal_px}
    sensor |= {f"sensor.{name}": value for name, value in noise.items()}
    return {
        "sim_bridge": {"max_range": max_range, **sensor},
        "perception": {"sensor.max_range": max_range, **sensor},
        "planner": {"min_range": min_range, "max_range": max_range},
    }


#: camera class -> parameter overrides (`area3d run --camera`); "ideal" is the default camera,
#: the paper's: no minimum range, 5 m, the noise coefficients as given at any focal length.
CAMERA_PRESETS: dict[str, dict[str, dict]] = {
    "ideal": {},
    # structured light, a Kinect v1 class sensor: the noise model's own (Nguyen et al. 2012,
    # fitted at its 580 px focal length), nothing nearer than 0.5 m, 4.5 m at most
    "kinect": _camera(0.5, 4.5, 580.0),
    # active stereo, a RealSense D435 class camera at 848x480 (datasheet: minimum depth 0.28 m,
    # under 2 % error to 2 m; 50 mm baseline, 87 degree field of view: f = 424 px): depth from
    # disparity, sigma_z = z^2 sigma_d / (f b) with a 0.08 px subpixel match, 0.0038 z^2 m
    "d435": _camera(0.28, 3.0, 424.0, sigma_a=0.0005, sigma_b=0.0038, sigma_z0=0.0),
}


def camera_preset(name: str) -> dict[str, dict]:
    """The parameter overrides of the camera class `name`."""
    if name not in CAMERA_PRESETS:
        raise ValueError(f"camera: got {name!r}, expected one of {sorted(CAMERA_PRESETS)}")
    return CAMERA_PRESETS[name]


def preset(name: str) -> dict[str, dict]:
    """The parameter overrides of the run preset `name`."""
    if name not in RUN_PRESETS:
        raise ValueError(f"policy: got {name!r}, expected one of {sorted(RUN_PRESETS)}")
    return RUN_PRESETS[name]


def episode_specs(
    scene: str,
    policy: str,
    seed: int,
    budget: int,
    mode: str = "closed_loop",
    overrides: Mapping[str, Mapping] | None = None,
    params_file: Path | None = None,
    nodes: tuple[tuple[str, str], ...] = GRAPH_NODES,
) -> list[NodeSpec]:
    """The graph's node specs for one episode: the bundled parameters (or `params_file`) <- what
    the scene tells the planner and semantics <- the preset <- the episode (scene, budget, mode,
    seed) <- `overrides`. The episode's seed also offsets the camera's noise seed, so that seeds
    differ in the simulated sensor noise as well as in the planner's random choices."""
    episode = {
        "sim_bridge": {"scene": scene},
        "planner": {"budget": int(budget), "mode": mode, "seed": int(seed)},
    }
    specs = build_graph(
        load_parameters(params_file), merge(preset(policy), episode, overrides), nodes
    )
    for spec in specs:
        if spec.name == "sim_bridge":
            spec.parameters["noise_seed"] = int(spec.parameters.get("noise_seed", 0)) + int(seed)
    return specs
