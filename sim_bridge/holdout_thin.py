"""Hold-out scene `thin_objects`: thin and textureless objects on a floor (a stool on thin legs,
a floor lamp, a wire rack, a glossy bowl, one large plain surface)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from sim_bridge import meshes
from sim_bridge.holdout_parts import (
    lights,
    place_apart,
    plain_material,
    scene_folder,
    seeded_rng,
    vec3,
)
from sim_bridge.mjcf import Mjcf, floor_plane, mesh_asset, mesh_body

# Thin and textureless objects on a floor: a stool with thin splayed legs, a floor lamp (a thin
# pole, a plain lamp shade), a wire rack, a glossy bowl, and one large plain surface (a cabinet, a
# screen or a low table's top), all within this area (x, y) of the floor.
THIN_AREA = (1.8, 1.3)


def _shade(bottom: float, top: float, height: float) -> trimesh.Trimesh:
    """An open lamp shade: a truncated cone shell 3 mm thick, `bottom` and `top` radii, metres."""
    t = 0.003
    profile = np.array(
        [(bottom, 0.0), (top, height), (top - t, height), (bottom - t, 0.0), (bottom, 0.0)]
    )
    return meshes._merge([meshes.revolve(profile[::-1], sections=32)])


def write_thin_objects(folder: Path, seed: int = 0) -> Path:
    """Write thin and textureless things on a floor into `folder` and return its MJCF path
    (`thin_objects_s{seed}.xml`).

    A stool with thin splayed legs, a floor lamp (a thin pole, a plain lamp shade), a wire rack, a
    glossy bowl (high specular, no texture), and one large plain surface: a standing screen, a
    cabinet or a low table with a plain top, by seed modulo 3 (the bowl stands on the low table,
    else on the stool). Everything stands on a floor plane, placed apart at sampled positions.
    """
    rng = seeded_rng(seed)
    folder = scene_folder(folder)
    name = f"thin_objects_s{seed}"
    doc = Mjcf(name)
    floor = doc.material(folder, "floor", "checker", (110, 100, 90), (160, 150, 135), repeat=(3, 3))
    wood = doc.material(folder, "wood", "stripes", (120, 80, 45), (170, 120, 70), repeat=(2, 2))
    metal = plain_material(doc, "metal", (60, 60, 65), specular=0.5, shininess=0.6)
    shade = plain_material(doc, "shade", rng.uniform(200, 245, 3), specular=0.05)
    glossy = plain_material(
        doc, "glossy", rng.uniform(20, 200, 3), specular=1.0, shininess=1.0, reflectance=0.5
    )
    surface = plain_material(doc, "plain", rng.uniform(150, 235, 3), specular=0.2)
    large = ("screen", "cabinet", "low_table")[seed % 3]  # seeds 0, 1, 2 show each
    seat_r, seat_z = rng.uniform(0.14, 0.18), rng.uniform(0.45, 0.65)
    splay = seat_r * 0.7 + rng.uniform(0.06, 0.1)  # leg foot radius
    lamp_r = rng.uniform(0.17, 0.22)
    rack = meshes.wire_rack(size=0.12)
    rack_scale = rng.uniform(2.5, 3.2)
    big = {
        "cabinet": np.array(
            [rng.uniform(0.5, 0.75), rng.uniform(0.35, 0.45), rng.uniform(0.5, 0.8)]
        ),
        "screen": np.array([rng.uniform(0.8, 1.0), 0.03, rng.uniform(1.0, 1.3)]),
        "low_table": np.array(
            [rng.uniform(0.7, 0.9), rng.uniform(0.45, 0.55), rng.uniform(0.35, 0.45)]
        ),
    }[large]
    radii = np.array(
        [
            splay + 0.03,
            lamp_r + 0.02,
            np.linalg.norm(rack.extents[:2]) / 2 * rack_scale,
            np.linalg.norm(big[:2]) / 2,
        ]
    )
    half = np.array(THIN_AREA) / 2
    order = np.argsort(-radii)  # the largest first: rejection sampling finds room for it
    where = np.zeros((4, 2))
    for attempt in range(20):  # a few fresh draws when the first ones leave no room
        try:
            where[order] = place_apart(rng, radii[order], -half, half, [])
            break
        except RuntimeError:
            if attempt == 19:
                raise
    # The stool: a seat on three or four thin legs splayed out to the floor.
    (x, y), legs = where[0], int(rng.integers(3, 5))
    doc.cylinder("stool_seat", [x, y, seat_z - 0.015], seat_r, 0.03, wood)
    for i in range(legs):
        a = 2 * np.pi * i / legs + rng.uniform(0, 0.3)
        top = [x + 0.6 * seat_r * np.cos(a), y + 0.6 * seat_r * np.sin(a), seat_z - 0.03]
        foot = [x + splay * np.cos(a), y + splay * np.sin(a), 0.011]
        doc.bodies.append(
            f'<geom name="stool_leg{i}" type="capsule" fromto="{vec3(top)} {vec3(foot)}" size="0.011" material="{metal}"/>'
        )
    # The floor lamp: a base disc, a thin pole and an open shade at its top.
    (x, y), pole_h = where[1], rng.uniform(1.35, 1.6)
    doc.cylinder("lamp_base", [x, y, 0.0125], rng.uniform(0.12, 0.15), 0.025, metal)
    doc.cylinder("lamp_pole", [x, y, 0.025 + pole_h / 2], rng.uniform(0.008, 0.012), pole_h, metal)
    cone = mesh_asset(
        doc,
        folder,
        "lamp_shade",
        _shade(lamp_r, lamp_r * rng.uniform(0.55, 0.7), rng.uniform(0.22, 0.28)),
        [1, 1, 1],
    )
    mesh_body(doc, "lamp_shade", cone, [x, y, 0.025 + pole_h - 0.12], 0.0, shade)
    # The wire rack on the floor.
    asset = mesh_asset(doc, folder, "wire_rack", rack, [rack_scale] * 3)
    mesh_body(doc, "wire_rack", asset, [*where[2], 0.0], rng.uniform(-np.pi, np.pi), metal)
    # The large plain surface, and the glossy bowl on the low table or on the stool.
    (x, y), (bx, by, bz) = where[3], big
    bowl = mesh_asset(
        doc, folder, "bowl", meshes.bowl(radius=rng.uniform(0.08, 0.11), height=0.06), [1, 1, 1]
    )
    bowl_at = [*where[0], seat_z]
    if large == "cabinet":
        doc.box("cabinet", [x, y, bz / 2], big, surface)
    elif large == "screen":
        yaw = rng.uniform(-0.6, 0.6)
        doc.bodies.append(
            f'<body name="screen" pos="{x:.4f} {y:.4f} 0" euler="0 0 {yaw:.4f}">'
            f'<geom name="screen_panel" type="box" pos="0 0 {0.06 + bz / 2:.4f}" size="{bx / 2:.4f} {by / 2:.4f} {bz / 2:.4f}" material="{surface}"/>'
            f'<geom name="screen_foot0" type="box" pos="{-bx / 2 + 0.05:.4f} 0 0.03" size="0.025 0.15 0.03" material="{metal}"/>'
            f'<geom name="screen_foot1" type="box" pos="{bx / 2 - 0.05:.4f} 0 0.03" size="0.025 0.15 0.03" material="{metal}"/>'
            "</body>"
        )
    else:
        doc.box("low_table_top", [x, y, bz - 0.015], [bx, by, 0.03], surface)
        for i, (a, b) in enumerate([(-1, -1), (-1, 1), (1, -1), (1, 1)]):
            doc.cylinder(
                f"low_table_leg{i}",
                [x + a * (bx / 2 - 0.04), y + b * (by / 2 - 0.04), (bz - 0.03) / 2],
                0.012,
                bz - 0.03,
                metal,
            )
        bowl_at = [x + rng.uniform(-0.1, 0.1) * bx, y, bz]
    mesh_body(doc, "bowl", bowl, bowl_at, 0.0, glossy)
    return doc.write(folder / f"{name}.xml", lights(rng, specular=0.6), floor_plane(floor))
