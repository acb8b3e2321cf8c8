"""Scenes by name or path: the bundled ones in `sim_bridge/scenes/<name>/scene.xml` with a sidecar
`scene.json`, and any other MJCF file, its metadata derived from its geometry when no sidecar is
found (`scene_layout`: level, ROI, workspace; `derived_views`: initial and held-out views).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from sim_bridge.derived_views import object_views, room_views
from sim_bridge.geoms import solid_geom_ids
from sim_bridge.scene import GAMMA, TAU, Scene
from sim_bridge.scene_layout import geometry_boxes, scene_layout

SCENES_DIR = Path(__file__).resolve().parent / "scenes"


# what a derived scene may be: a camera reconstructs objects of centimetres (tau 1 cm) up to rooms
MIN_GEOM_RADIUS_M = 0.005
MAX_ROI_EXTENT_M = 50.0


def list_scenes() -> list[str]:
    """Names of the bundled scenes."""
    return sorted(p.parent.name for p in SCENES_DIR.glob("*/scene.xml"))


def load_scene(name_or_path: str | Path) -> Scene:
    """A bundled scene by name, or any MJCF file by path (metadata from a sidecar JSON or derived)."""
    text = str(name_or_path)
    bundled = SCENES_DIR / text / "scene.xml"
    if "/" not in text and not text.endswith(".xml") and bundled.is_file():
        path = bundled
    else:
        path = Path(text).expanduser()
        if not path.is_file():
            raise ValueError(
                f"scene: got {text!r}, expected one of {list_scenes()} or an existing MJCF file path"
            )
    path = path.resolve()
    for sidecar in (path.with_suffix(".json"), path.parent / "scene.json"):
        if sidecar.is_file():
            return _from_sidecar(path, sidecar)
    return derive_scene(path)


def scene_reference(scene: Scene) -> str:
    """How a run records `scene` so that `load_scene` finds it again from any directory: a
    bundled scene by its name, any other by its absolute path."""
    bundled = (SCENES_DIR / scene.name / "scene.xml").resolve()
    return scene.name if Path(scene.mjcf_path).resolve() == bundled else str(scene.mjcf_path)


#: a sidecar's fields: (what it is, the array shape or None for a number/string)
SIDECAR_FIELDS = {
    "workspace_min": (3,),
    "workspace_max": (3,),
    "roi_min": (3,),
    "roi_max": (3,),
    "initial_views": (-1, 4, 4),
    "eval_views": (-1, 4, 4),
}


def _from_sidecar(path: Path, sidecar: Path) -> Scene:
    """The scene with a sidecar's metadata; the fields it leaves out derived from the geometry
    as without one. A sidecar that is no JSON object, or a field of the wrong kind, refused with
    the file and the field named."""
    try:
        meta = json.loads(sidecar.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"scene sidecar {str(sidecar)!r}: not JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise ValueError(
            f"scene sidecar {str(sidecar)!r}: got {type(meta).__name__}, expected an object"
        )
    derived = None if set(SIDECAR_FIELDS) <= set(meta) else derive_scene(path, meta.get("name"))
    level = meta.get("level", derived.level if derived else "object")
    if level not in GAMMA:
        raise ValueError(
            f"scene sidecar {str(sidecar)!r}: level: got {level!r}, expected one of {list(GAMMA)}"
        )
    values = {}
    for name, shape in SIDECAR_FIELDS.items():
        if name not in meta:
            values[name] = getattr(derived, name)
            continue
        try:
            value = np.asarray(meta[name], dtype=np.float64)
            value = value.reshape(shape) if shape[0] == -1 else value
        except (TypeError, ValueError) as exc:
            raise ValueError(f"scene sidecar {str(sidecar)!r}: {name}: {exc}") from exc
        if value.shape[1:] != shape[1:] or (shape[0] != -1 and value.shape != shape):
            raise ValueError(
                f"scene sidecar {str(sidecar)!r}: {name}: got shape {value.shape}, expected {shape}"
            )
        if not np.all(np.isfinite(value)):
            raise ValueError(f"scene sidecar {str(sidecar)!r}: {name}: got non-finite values")
        values[name] = value
    return Scene(
        name=str(meta.get("name", path.stem)),
        level=level,
        mjcf_path=path,
        gamma=float(meta.get("gamma", GAMMA[level])),
        tau=float(meta.get("tau", TAU[level])),
        **values,
    )


def scene_to_json(scene: Scene) -> str:
    """The sidecar JSON text of `scene` (what `load_scene` reads back)."""
    meta = {
        "name": scene.name,
        "level": scene.level,
        "gamma": scene.gamma,
        "tau": scene.tau,
        "workspace_min": np.round(scene.workspace_min, 6).tolist(),
        "workspace_max": np.round(scene.workspace_max, 6).tolist(),
        "roi_min": np.round(scene.roi_min, 6).tolist(),
        "roi_max": np.round(scene.roi_max, 6).tolist(),
        "initial_views": np.round(scene.initial_views, 7).tolist(),
        "eval_views": np.round(scene.eval_views, 7).tolist(),
    }
    return json.dumps(meta, indent=1)


def derive_scene(path: Path, name: str | None = None) -> Scene:
    """Metadata for an MJCF file that has none, from its geometry (rules in sim_bridge/README.md).

    Fills every `Scene` field: `level` ("room" when walls enclose the scene on 3 or 4 sides or its
    footprint, walls beside it left out, is large, else "object"), `roi_min/max` (object level: the
    objects on the highest large support surface plus a rim of that surface, up to the faces of
    the walls beside them; room level: the interior inside the walls), workspace (object level: the
    ROI grown by a margin, above the support, in front of the walls; room level: the interior
    shrunk by a margin, at robot heights), `initial_views` (4 on an arc on the open side / 15
    spread inside the room) and `eval_views` (rings all around or over the open side / spread
    inside the room), every view clear of geometry, plus `gamma` and `tau` of the level.
    """
    scene = Scene(
        name=name or path.stem,
        level="object",
        mjcf_path=path,
        workspace_min=np.zeros(3),
        workspace_max=np.ones(3),
        roi_min=np.zeros(3),
        roi_max=np.ones(3),
        initial_views=np.zeros((0, 4, 4)),
        eval_views=np.zeros((0, 4, 4)),
        gamma=GAMMA["object"],
        tau=TAU["object"],
    )
    try:
        model, data = scene.model()
    except ValueError as err:  # MuJoCo's XML / compile errors do not name the file
        raise ValueError(
            # on one line: MuJoCo's message spans several
            f"scene file {str(path)!r}: MuJoCo could not load it: {' '.join(str(err).split())}"
        ) from err
    if len(solid_geom_ids(model)) == 0:  # (a scene of planes only)
        raise ValueError(
            f"scene file {str(path)!r}: no solid geoms, expected at least one visible geom that is not a plane"
        )
    solid = solid_geom_ids(model)
    largest = float(np.max(model.geom_rbound[solid])) if len(solid) else 0.0
    if largest < MIN_GEOM_RADIUS_M:
        raise ValueError(
            f"scene file {str(path)!r}: its largest solid geom reaches {largest:.2g} m from its "
            f"centre, expected objects of centimetres or more (an MJCF in other units than metres?)"
        )
    layout = scene_layout(*geometry_boxes(model, data))
    extent = float(np.max(layout["roi_max"] - layout["roi_min"]))
    if extent > MAX_ROI_EXTENT_M:
        raise ValueError(
            f"scene file {str(path)!r}: the region to reconstruct spans {extent:.3g} m, expected "
            f"at most {MAX_ROI_EXTENT_M:g} m (an MJCF in centimetres or millimetres?)"
        )
    level = layout["level"]
    scene.level = level
    scene.gamma, scene.tau = GAMMA[level], TAU[level]
    scene.roi_min, scene.roi_max = layout["roi_min"], layout["roi_max"]
    scene.workspace_min, scene.workspace_max = layout["workspace_min"], layout["workspace_max"]
    if level == "object":
        scene.initial_views, scene.eval_views = object_views(scene, layout)
    else:
        scene.initial_views, scene.eval_views = room_views(scene, layout)
    scene._cache.pop("gt", None)
    return scene
