"""The AREA3D node graph as data: which nodes run, from which module, with which parameters."""

from __future__ import annotations

import copy
import difflib
import importlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import yaml

from area3d_bringup.graph import GRAPH_NODES
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.parameters import BUILTIN_PARAMETERS, parameter_values

__all__ = [
    "GRAPH_NODES", "NodeSpec", "build_graph", "check_parameters", "load_parameters", "merge",
    "parse_override", "parse_overrides", "scene_parameters",
]  # fmt: skip

# Node sections of a parameter file apply to the node in any namespace.
ANY_NAMESPACE = "/**/"


@dataclass
class NodeSpec:
    """One node process: its ROS name, the module whose `main` runs it, its parameters."""

    name: str
    module: str
    parameters: dict = field(default_factory=dict)


def default_params_file() -> Path:
    """The bundled parameter file (`area3d_bringup/config/area3d.yaml`)."""
    return Path(str(resources.files("area3d_bringup") / "config" / "area3d.yaml"))


def load_parameters(path: Path | None = None) -> dict[str, dict]:
    """{node_name: {param: value}} from a ROS 2 parameter YAML file (`ros__parameters` sections)."""
    path = Path(path) if path is not None else default_params_file()
    if not path.is_file():
        raise FileNotFoundError(
            f"params file: got {str(path)!r}, expected an existing ROS 2 parameter YAML file"
        )
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise ValueError(f"params file {path}: not valid YAML: {_yaml_problem(err)}") from None
    if not isinstance(data, dict):
        raise ValueError(
            f"params file {path}: expected a mapping of node names, got {type(data).__name__}"
        )
    out: dict[str, dict] = {}
    for node_name, section in data.items():
        params = (section or {}).get("ros__parameters", {}) if isinstance(section, dict) else {}
        out[str(node_name).removeprefix(ANY_NAMESPACE).lstrip("/")] = dict(params or {})
    return out


def _yaml_problem(err: yaml.YAMLError) -> str:
    """What a YAML parser refused, on one line: the problem and where (line, column)."""
    mark = getattr(err, "problem_mark", None)
    problem = getattr(err, "problem", None) or str(err).splitlines()[0]
    return f"{problem} at line {mark.line + 1}, column {mark.column + 1}" if mark else problem


def scene_parameters(scene_name: str) -> dict[str, dict]:
    """What the planner and semantics are told about a scene, as a robot would be: the level's
    defaults, the region of interest and the workspace box (never the scene's geometry)."""
    from sim_bridge.scenes import load_scene

    scene = load_scene(scene_name)
    region = planner_region(scene)
    planner = {**region, "gamma": float(scene.gamma)}
    reconstruction = {k: region[k] for k in ("roi_min", "roi_max", "level")}
    return {
        "planner": planner,
        "semantics": {"num_initial_views": len(scene.initial_views)},
        "reconstruction": reconstruction,
    }


def merge(*layers: Mapping[str, Mapping] | None) -> dict[str, dict]:
    """{node: {param: value}} of parameter layers, a later layer's value winning per parameter
    (None layers are skipped; the inputs are not changed)."""
    merged: dict[str, dict] = {}
    for layer in layers:
        for node, values in (layer or {}).items():
            merged.setdefault(node, {}).update(values)
    return merged


def parse_override(text: str) -> tuple[str, str, object]:
    """`NODE.NAME=VALUE` -> (node, name, yaml-typed value)."""
    key, sep, raw = text.partition("=")
    node, dot, name = key.partition(".")
    if not sep or not dot or not node or not name:
        raise ValueError(f"--param: got {text!r}, expected NODE.NAME=VALUE, e.g. planner.eta=0.3")
    try:
        value = yaml.safe_load(raw) if raw else ""
    except yaml.YAMLError as err:
        raise ValueError(
            f"--param {key}: got {raw!r}, expected a YAML value ({_yaml_problem(err)})"
        ) from None
    return node, name, value


def parse_overrides(texts: Iterable[str]) -> dict[str, dict]:
    """Repeated `--param NODE.NAME=VALUE` -> {node: {name: yaml-typed value}}, a later text
    winning for the same parameter."""
    out: dict[str, dict] = {}
    for text in texts:
        node, name, value = parse_override(text)
        out.setdefault(node, {})[name] = value
    return out


def planner_region(scene) -> dict:
    """What the operator tells the planner about a sim_bridge scene: the region to reconstruct (a
    box), where the camera may go and the level. The planner gets nothing else of the scene."""
    return {
        "roi_min": [float(v) for v in scene.roi_min],
        "roi_max": [float(v) for v in scene.roi_max],
        "workspace_min": [float(v) for v in scene.workspace_min],
        "workspace_max": [float(v) for v in scene.workspace_max],
        "level": scene.level,
    }


# With stereo depth a lone match under this calibrated confidence (a periodic texture matched at
# the wrong disparity, floating in the air) makes no unknown space near a surface until a second
# frame hits its voxel (planner `unobserved_reach_confidence`; docs/results.md, "A lone stereo
# match in the air draws no views"); a depth camera's lone hit is a surface (0, the planner's).
STEREO_REACH_CONFIDENCE = 0.8


def stereo_min_range(camera: Mapping, perception: Mapping) -> float:
    """The nearest depth the stereo backend can measure on the simulated pair, metres: f B / (the
    disparities it searches, in full-size pixels). A surface nearer than that has a disparity
    beyond the search and is matched to a wrong, farther one (or to nothing). camera: sim_bridge's
    parameters, perception: perception's (their defaults where a value is not given)."""
    import math

    from area3d_perception.stereo import StereoParams
    from sim_bridge.camera import STEREO_BASELINE

    width = float(camera.get("width", 640))
    hfov_deg = float(camera.get("hfov_deg", 90.0))
    fx = width / 2.0 / math.tan(math.radians(hfov_deg) / 2.0)
    baseline = float(camera.get("stereo_baseline", STEREO_BASELINE))
    defaults = StereoParams()
    searched = int(perception.get("stereo.num_disparities", defaults.num_disparities)) * int(
        perception.get("stereo.downscale", defaults.downscale)
    )
    return fx * baseline / searched


def build_graph(
    params: dict[str, dict] | None = None,
    overrides: dict[str, dict] | None = None,
    nodes: tuple[tuple[str, str], ...] = GRAPH_NODES,
) -> list[NodeSpec]:
    """The node specs for one launch: what the camera's scene tells the planner <- bundled
    defaults (or `params`) <- `overrides`."""
    params = load_parameters() if params is None else params
    check_parameters(params, overrides)
    merged = merge(copy.deepcopy(params), overrides)
    names = {name for name, _ in nodes}
    scene = merged.get("sim_bridge", {}).get("scene")
    if scene and names & {"planner", "semantics", "reconstruction"}:
        merged = merge(scene_parameters(scene), merged)
    # The stereo backend matches the camera's right image: a simulated camera renders one then.
    if merged.get("perception", {}).get("backend") == "stereo" and "sim_bridge" in merged:
        merged["sim_bridge"].setdefault("stereo", True)
        if "planner" in names:
            planner = merged.setdefault("planner", {})
            near = stereo_min_range(merged["sim_bridge"], merged["perception"])
            planner["min_range"] = max(float(planner.get("min_range", 0.0)), near)
            planner.setdefault("unobserved_reach_confidence", STEREO_REACH_CONFIDENCE)
    shared = merged.get("**", {})
    specs = [NodeSpec(name, module, {**shared, **merged.get(name, {})}) for name, module in nodes]
    for spec in specs:  # a value the node would refuse is refused before anything starts
        try:
            parameter_values(_declared(spec.name), spec.parameters)
        except InputError as err:
            raise ValueError(f"{spec.name}.{err}") from None
    return specs


def check_parameters(
    params: Mapping[str, Mapping], overrides: Mapping[str, Mapping] | None
) -> None:
    """Refuse, before a node starts, the names a node would only warn about in its log: an
    override (`-p NODE.NAME=VALUE`) for a node the graph does not have, and a name that a graph
    node does not declare, in an override or in the node's section of the parameter file (the
    file may hold sections of other nodes of a robot's stack: those are theirs). Raises
    ValueError naming the node, the parameter and, where one is close, the declared name meant."""
    graph = [name for name, _ in GRAPH_NODES]
    for node in overrides or {}:
        if node not in graph and node != "**":
            raise ValueError(f"--param {node}.*: got node {node!r}, expected one of {graph}")
    for source, layer in (("params file", params), ("--param", overrides or {})):
        for node, values in layer.items():
            if node not in graph:
                continue
            declared = {p.name for p in _declared(node)} | BUILTIN_PARAMETERS
            for name in values:
                if name not in declared:
                    close = difflib.get_close_matches(name, declared, 1)
                    hint = f" (did you mean {close[0]!r}?)" if close else ""
                    raise ValueError(
                        f"{source} {node}.{name}: got a name that {node} does not declare{hint}; "
                        f"its package README and `ros2 param list /{node}` list its parameters"
                    )


def _declared(node: str) -> tuple:
    """The `Param`s node `node` declares (its module's PARAMS)."""
    return importlib.import_module(dict(GRAPH_NODES)[node]).PARAMS


class _NoAliases(yaml.SafeDumper):
    """A value shared by two nodes (the region both the planner and the reconstruction get) is
    written out twice: rcl's parameter parser refuses YAML aliases."""

    def ignore_aliases(self, data) -> bool:
        return True


def write_params_file(specs: list[NodeSpec], path: Path) -> Path:
    """Write the specs' parameters as one ROS 2 parameter YAML file (what each node process reads)."""
    data = {ANY_NAMESPACE + spec.name: {"ros__parameters": spec.parameters} for spec in specs}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.dump(data, Dumper=_NoAliases, sort_keys=False))
    return path
