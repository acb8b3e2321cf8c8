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
    # range, direction or resolution term); `--mode batch` plans every view from O_0 as the paper
    # does. Candidate positions and the orientation fan stay the project's.
    "paper": {
        "planner": {
            "policy": "area3d",
            "geometric_rule": "mean",
            "unobserved_uncertainty": 0.0,
            "gain_rule": "held",
            "range_profile": False,
            "repeat_gain": 1.0,
            "pixels_per_voxel": PAPER_PIXELS_PER_VOXEL,
        }
    },
}


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
