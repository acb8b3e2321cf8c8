"""Scanned real objects for the scenes: six textured YCB scans vendored in `sim_bridge/scanned/`
(source, licences and changes in its NOTICE.md), read offline, placed standing on a surface.

A scan's file frame has its base near z = 0 with the object off-centre in x and y; `footprint`
reads the vertices from the `.msh` file (MuJoCo's binary mesh: four int32 counts, then float32
vertices, normals and texture coordinates, then int32 faces) so that `place_scanned` can stand
the object on a surface with its footprint centred where it is asked to be.
"""

from __future__ import annotations

import functools
import shutil
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from sim_bridge.mjcf import Mjcf, vec

SCANNED_DIR = Path(__file__).resolve().parent / "scanned"
SCANNED_OBJECTS = (
    "003_cracker_box",
    "004_sugar_box",
    "005_tomato_soup_can",
    "006_mustard_bottle",
    "010_potted_meat_can",
    "035_power_drill",
)


@dataclass(frozen=True)
class Footprint:
    """A scan's extent in its own frame, metres: centre of its (x, y) bounds, radius of the
    disc around that centre that holds it, lowest and highest z."""

    centre_xy: np.ndarray
    radius: float
    z_min: float
    z_max: float


def read_msh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) float32 vertices and (F, 3) int32 faces of a MuJoCo `.msh` file."""
    data = Path(path).read_bytes()
    if len(data) < 16:
        raise ValueError(f"mesh file {str(path)!r}: got {len(data)} bytes, expected a .msh header")
    nv, nn, nt, nf = (int(n) for n in np.frombuffer(data[:16], np.int32))
    expected = 16 + 4 * (3 * nv + 3 * nn + 2 * nt + 3 * nf)
    if min(nv, nn, nt, nf) < 0 or nv == 0 or nf == 0 or len(data) != expected:
        raise ValueError(
            f"mesh file {str(path)!r}: got {len(data)} bytes for counts (vertices {nv}, normals "
            f"{nn}, texcoords {nt}, faces {nf}), expected {expected} bytes and non-zero counts"
        )
    floats = np.frombuffer(data[16 : 16 + 4 * (3 * nv + 3 * nn + 2 * nt)], np.float32)
    faces = np.frombuffer(data[expected - 12 * nf :], np.int32).reshape(nf, 3)
    return floats[: 3 * nv].reshape(nv, 3), faces


def _check(name: str) -> None:
    if name not in SCANNED_OBJECTS:
        raise ValueError(f"scanned object: got {name!r}, expected one of {list(SCANNED_OBJECTS)}")


@functools.cache
def footprint(name: str) -> Footprint:
    """The extent of the scan `name` (one of SCANNED_OBJECTS) in its file frame (read once)."""
    _check(name)
    vertices, _ = read_msh(SCANNED_DIR / f"{name}.msh")
    lo, hi = vertices.min(axis=0).astype(float), vertices.max(axis=0).astype(float)
    centre = (lo[:2] + hi[:2]) / 2
    radius = float(np.linalg.norm(vertices[:, :2] - centre, axis=1).max())
    return Footprint(centre, radius, lo[2], hi[2])


def add_scanned(doc: Mjcf, folder: Path | None, name: str) -> str:
    """Add the mesh, texture and material assets of the scan `name` to `doc`; returns the mesh
    (and material) name. With `folder`, the files are copied there and named relative to it (a
    scene folder that can be moved as a whole); without, the assets name the vendored files by
    a path relative to a bundled scene's folder (`scenes/<scene>/`)."""
    _check(name)
    if name in doc.textures:
        return name
    if folder is None:
        stem = f"../../{SCANNED_DIR.name}/{name}"
    else:
        for suffix in (".msh", ".png"):
            shutil.copyfile(SCANNED_DIR / f"{name}{suffix}", Path(folder) / f"{name}{suffix}")
        stem = name
    doc.assets += [
        f'<mesh name="{name}" file="{stem}.msh"/>',
        f'<texture name="{name}" type="2d" file="{stem}.png"/>',
        f'<material name="{name}" texture="{name}" specular="0.2" shininess="0.3"/>',
    ]
    doc.textures.add(name)
    return name


def place_scanned(doc: Mjcf, body: str, name: str, xy, top: float, yaw: float) -> None:
    """Stand the scan `name` (its assets added by `add_scanned`) on the surface at height `top`,
    its footprint centred at `xy` (metres), turned by `yaw` (radians) about z."""
    fp = footprint(name)
    quat = np.zeros(4)
    mujoco.mju_euler2Quat(quat, np.array([0.0, 0.0, yaw]), "xyz")
    c, s = np.cos(yaw), np.sin(yaw)
    turned = np.array(
        [c * fp.centre_xy[0] - s * fp.centre_xy[1], s * fp.centre_xy[0] + c * fp.centre_xy[1]]
    )
    pos = np.array([*(np.asarray(xy, dtype=float) - turned), top - fp.z_min])
    doc.bodies.append(
        f'<body name="{body}" pos="{vec(pos)}" quat="{vec(quat)}">'
        f'<geom type="mesh" mesh="{name}" material="{name}"/></body>'
    )
