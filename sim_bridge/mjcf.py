"""Writing MuJoCo scenes: the MJCF document (assets, textured materials, geoms), the furniture the
scene generators build rooms and tables from, and the blank Scene their metadata is filled into.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from sim_bridge import meshes
from sim_bridge.scene import GAMMA, TAU, Scene
from sim_bridge.textures import write_texture

WIDTH, HEIGHT = 640, 480  # offscreen buffer for the default camera resolution
ROOM_HALF = (3.0, 2.5)  # metres: 6 m x 5 m interior
WALL_HEIGHT = 2.6
WALL_THICK = 0.1


@dataclass
class Mjcf:
    """Accumulates MJCF assets and world-body children."""

    name: str
    assets: list[str] = field(default_factory=list)
    bodies: list[str] = field(default_factory=list)
    textures: set = field(default_factory=set)

    def material(self, folder: Path, name: str, kind: str, a, b, repeat=(1, 1), seed=0) -> str:
        if name not in self.textures:
            write_texture(folder / f"{name}.png", kind, a, b, seed)
            self.assets.append(f'<texture name="{name}" type="2d" file="{name}.png"/>')
            self.assets.append(
                f'<material name="{name}" texture="{name}" texrepeat="{repeat[0]} {repeat[1]}" texuniform="{"true" if repeat != (1, 1) else "false"}" specular="0.1"/>'
            )
            self.textures.add(name)
        return name

    def box(self, name, centre, extents, material) -> None:
        c, h = np.asarray(centre), np.asarray(extents) / 2
        self.bodies.append(
            f'<geom name="{name}" type="box" pos="{vec(c)}" size="{vec(h)}" material="{material}"/>'
        )

    def cylinder(self, name, centre, radius, height, material) -> None:
        self.bodies.append(
            f'<geom name="{name}" type="cylinder" pos="{vec(centre)}" size="{radius:.4f} {height / 2:.4f}" material="{material}"/>'
        )

    def write(self, path: Path, lights: list[str], extra_world: str = "") -> Path:
        """Write the document (`xml`) to `path` and return the path."""
        path.write_text(self.xml(lights, extra_world))
        return path

    def xml(self, lights: list[str], extra_world: str = "") -> str:
        return f"""<mujoco model="{self.name}">
  <compiler angle="radian" inertiafromgeom="false"/>
  <option timestep="0.002"/>
  <visual>
    <global offwidth="{WIDTH}" offheight="{HEIGHT}"/>
    <quality offsamples="0"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.45 0.45 0.45" specular="0.05 0.05 0.05"/>
  </visual>
  <asset>
    {chr(10).join("    " + a for a in self.assets).strip()}
  </asset>
  <worldbody>
    {chr(10).join("    " + a for a in lights).strip()}
    {extra_world}
    {chr(10).join("    " + b for b in self.bodies).strip()}
  </worldbody>
</mujoco>
"""


def floor_plane(material: str) -> str:
    """The infinite floor plane at z = 0 with `material`, as a world-body child."""
    return f'<geom name="floor" type="plane" size="0 0 0.05" material="{material}"/>'


def vec(x) -> str:
    return " ".join(f"{float(a):.5f}" for a in np.asarray(x).ravel())


def blank_scene(name: str, level: str, folder: Path) -> Scene:
    z3 = np.zeros(3)
    return Scene(
        name,
        level,
        folder / "scene.xml",
        z3,
        z3,
        z3,
        z3,
        np.zeros((0, 4, 4)),
        np.zeros((0, 4, 4)),
        GAMMA[level],
        TAU[level],
    )


def room_shell(
    doc: Mjcf,
    folder: Path,
    wall_kind=("noise", (215, 210, 195), (235, 232, 222)),
    half: tuple[float, float] = ROOM_HALF,
) -> None:
    """Floor slab and four walls around an interior of 2 half[0] x 2 half[1] m centred on the
    origin, with a doorway in the north wall."""
    hx, hy = half
    floor = doc.material(folder, "floor", "stripes", (130, 95, 60), (175, 135, 90), repeat=(3, 3))
    wall = doc.material(folder, "wall", *wall_kind, repeat=(2, 2), seed=5)
    t, h = WALL_THICK, WALL_HEIGHT
    doc.box("floor", [0, 0, -0.05], [2 * hx + 2 * t, 2 * hy + 2 * t, 0.1], floor)
    doc.box("wall_south", [0, -hy - t / 2, h / 2], [2 * hx + 2 * t, t, h], wall)
    doc.box("wall_west", [-hx - t / 2, 0, h / 2], [t, 2 * hy, h], wall)
    doc.box("wall_east", [hx + t / 2, 0, h / 2], [t, 2 * hy, h], wall)
    # North wall with a doorway (1 m wide, 2.1 m high) so the room is not a closed box.
    door_x0, door_x1 = 1.2, 2.2
    doc.box(
        "wall_north_a", [(-hx - t + door_x0) / 2, hy + t / 2, h / 2], [door_x0 + hx + t, t, h], wall
    )
    doc.box(
        "wall_north_b", [(door_x1 + hx + t) / 2, hy + t / 2, h / 2], [hx + t - door_x1, t, h], wall
    )
    doc.box(
        "wall_north_lintel",
        [(door_x0 + door_x1) / 2, hy + t / 2, (h + 2.1) / 2],
        [door_x1 - door_x0, t, h - 2.1],
        wall,
    )


def mesh_asset(doc: Mjcf, folder: Path, name: str, mesh, scale) -> str:
    meshes.write_obj(mesh, folder / f"{name}.obj")
    doc.assets.append(f'<mesh name="{name}" file="{name}.obj" scale="{vec(scale)}"/>')
    return name


def table4(doc, name, centre_xy, size, height, top_mat, leg_mat) -> None:
    x, y = centre_xy
    sx, sy = size
    doc.box(f"{name}_top", [x, y, height - 0.02], [sx, sy, 0.04], top_mat)
    for i, (a, b) in enumerate([(-1, -1), (-1, 1), (1, -1), (1, 1)]):
        doc.cylinder(
            f"{name}_leg{i}",
            [x + a * (sx / 2 - 0.06), y + b * (sy / 2 - 0.06), (height - 0.04) / 2],
            0.025,
            height - 0.04,
            leg_mat,
        )


def mesh_body(doc, name, mesh_name, pos, yaw, material) -> None:
    quat = np.zeros(4)
    mujoco.mju_euler2Quat(quat, np.array([0.0, 0.0, yaw]), "xyz")
    doc.bodies.append(
        f'<body name="{name}" pos="{vec(pos)}" quat="{vec(quat)}"><geom type="mesh" mesh="{mesh_name}" material="{material}"/></body>'
    )
