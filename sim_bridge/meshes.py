"""Procedural object meshes for the bundled scenes (metres, z up, resting on z = 0).

Every generator returns a `trimesh.Trimesh` with per-vertex texture coordinates in
`mesh.visual.uv` (cylindrical projection), small enough (< 2k faces) to ship as .obj.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh


def _with_uv(mesh: trimesh.Trimesh, repeat: float = 2.0) -> trimesh.Trimesh:
    """Attach cylindrical texture coordinates: u around z, v along z (repeated `repeat` times)."""
    v = mesh.vertices
    centre = v.mean(axis=0)
    u = (np.arctan2(v[:, 1] - centre[1], v[:, 0] - centre[0]) / (2 * np.pi) + 0.5) * repeat
    span = max(float(np.ptp(v[:, 2])), 1e-6)
    w = (v[:, 2] - v[:, 2].min()) / span * repeat
    mesh.visual = trimesh.visual.TextureVisuals(uv=np.stack([u, w], axis=1))
    return mesh


def _on_ground(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Centre in x, y and lift so the lowest vertex sits at z = 0."""
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return mesh


def _merge(parts: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    return _with_uv(_on_ground(trimesh.util.concatenate(parts)))


def _box(extents, centre) -> trimesh.Trimesh:
    return trimesh.creation.box(
        extents=extents, transform=trimesh.transformations.translation_matrix(centre)
    )


def revolve(profile: np.ndarray, sections: int = 32) -> trimesh.Trimesh:
    """Surface of revolution about z of a (N, 2) polyline of (radius, z) points, metres."""
    profile = np.asarray(profile, dtype=np.float64)
    return trimesh.creation.revolve(profile, sections=sections)


def tube(path: np.ndarray, radius: float, sides: int = 8, closed: bool = False) -> trimesh.Trimesh:
    """Tube of circular cross-section `radius` (m) swept along a (N, 3) polyline path.

    Open paths get flat end caps so the tube is watertight.
    """
    path = np.asarray(path, dtype=np.float64)
    n = len(path)
    tangent = np.gradient(path, axis=0)
    if closed:
        tangent = np.roll(path, -1, axis=0) - np.roll(path, 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    # Parallel-transport-free frame: any vector not parallel to the tangent.
    ref = np.where(np.abs(tangent[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    normal = np.cross(tangent, ref)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    binormal = np.cross(tangent, normal)
    angle = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = (
        np.cos(angle)[None, :, None] * normal[:, None]
        + np.sin(angle)[None, :, None] * binormal[:, None]
    )
    vertices = (path[:, None] + radius * ring).reshape(-1, 3)
    i = np.arange(n if closed else n - 1)[:, None]
    j = np.arange(sides)[None, :]
    a = i * sides + j
    b = i * sides + (j + 1) % sides
    c = ((i + 1) % n) * sides + j
    d = ((i + 1) % n) * sides + (j + 1) % sides
    # Winding (a, b, c) makes the normals point away from the path (outward).
    faces = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)]
    )
    if not closed:
        start = len(vertices)
        vertices = np.vstack([vertices, path[0], path[-1]])
        cap0 = np.stack([np.full(sides, start), (j[0] + 1) % sides, j[0]], -1)
        last = (n - 1) * sides
        cap1 = np.stack([np.full(sides, start + 1), last + j[0], last + (j[0] + 1) % sides], -1)
        faces = np.vstack([faces, cap0, cap1])
    return trimesh.Trimesh(vertices, faces, process=True)


def mug(radius: float = 0.04, height: float = 0.095, wall: float = 0.005) -> trimesh.Trimesh:
    """Open-top mug with a handle: concave (the inside is only seen from above)."""
    profile = [
        (0.0, wall),
        (radius - wall, wall),
        (radius - wall, height),
        (radius, height),
        (radius, 0.0),
        (0.0, 0.0),
    ]
    body = revolve(np.array(profile)[::-1], sections=28)
    t = np.linspace(-np.pi / 2, np.pi / 2, 12)
    arc = np.stack(
        [radius + 0.028 * np.cos(t) - 0.004, np.zeros_like(t), height / 2 + 0.03 * np.sin(t)], 1
    )
    return _merge([body, tube(arc, 0.006, sides=8)])


def bowl(radius: float = 0.07, height: float = 0.05, wall: float = 0.005) -> trimesh.Trimesh:
    """Hemispherical bowl on a foot ring."""
    t = np.linspace(0, np.pi / 2, 9)
    outer = np.stack(
        [0.35 * radius + (radius - 0.35 * radius) * np.sin(t), height * (1 - np.cos(t))], 1
    )
    inner = outer[::-1] * [(radius - wall) / radius, 1.0] + [0.0, wall]
    profile = np.vstack([[0.0, 0.0], outer, inner, [0.0, wall]])
    return _merge([revolve(profile, sections=28)])


def vase(radius: float = 0.035, height: float = 0.16) -> trimesh.Trimesh:
    """Closed vase with a bulging belly and a narrow neck."""
    z = np.linspace(0, height, 14)
    r = (
        radius
        * (0.6 + 0.5 * np.sin(np.pi * z / height * 1.3) ** 2)
        * np.where(z > 0.8 * height, 0.6, 1.0)
    )
    profile = np.vstack([[0.0, 0.0], np.stack([r, z], 1), [0.0, height]])
    return _merge([revolve(profile, sections=24)])


def toy_chair(scale: float = 0.12) -> trimesh.Trimesh:
    """Small chair: seat, back rest and four thin legs (thin structures, self-occlusion)."""
    s = scale
    leg = 0.012 * s / 0.12
    parts = [_box([s, s, 0.1 * s], [0, 0, 0.55 * s])]
    for x in (-0.45 * s, 0.45 * s):
        for y in (-0.45 * s, 0.45 * s):
            parts.append(_box([leg, leg, 0.5 * s], [x, y, 0.25 * s]))
    parts.append(_box([0.08 * s, s, 0.7 * s], [-0.46 * s, 0, 0.95 * s]))
    return _merge(parts)


def lamp(height: float = 0.2) -> trimesh.Trimesh:
    """Desk lamp: disc base, bent arm, conical open shade."""
    base = revolve(
        np.array([(0.0, 0.012), (0.05, 0.012), (0.05, 0.0), (0.0, 0.0)])[::-1], sections=20
    )
    arm_path = np.array(
        [
            [0.0, 0.0, 0.01],
            [0.0, 0.0, 0.6 * height],
            [0.06, 0.0, height],
            [0.09, 0.0, 0.92 * height],
        ]
    )
    t = np.linspace(0, 1, 10)[:, None]
    arm = tube(
        np.vstack(
            [
                arm_path[0] + t * (arm_path[1] - arm_path[0]),
                arm_path[1] + t[1:] * (arm_path[2] - arm_path[1]),
                arm_path[2] + t[1:] * (arm_path[3] - arm_path[2]),
            ]
        ),
        0.006,
    )
    shade = revolve(
        np.array([(0.015, 0.0), (0.045, -0.06), (0.041, -0.06), (0.011, 0.0), (0.015, 0.0)])[::-1],
        sections=20,
    )
    shade.apply_translation([0.09, 0.0, 0.95 * height])
    return _merge([base, arm, shade])


def blob(radius: float = 0.06, seed: int = 0, bumps: int = 6) -> trimesh.Trimesh:
    """Bunny-like lumpy body: an icosphere displaced by smooth random lobes, plus two ears."""
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    d = rng.normal(size=(bumps, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    amp = rng.uniform(0.08, 0.25, bumps)
    n = sphere.vertices
    scale = 1.0 + (amp[None] * np.exp(-((1 - n @ d.T) / 0.25))).sum(1)
    sphere.vertices = n * scale[:, None] * radius * np.array([1.2, 0.9, 0.8])
    parts = [sphere]
    for y in (-0.35, 0.35):
        ear = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
        ear.vertices *= radius * np.array([0.18, 0.12, 0.55])
        ear.apply_translation([0.6 * radius, y * radius, 0.9 * radius])
        parts.append(ear)
    return _merge(parts)


def tunnel_block(size: float = 0.1, hole: float = 0.05) -> trimesh.Trimesh:
    """Box with a rectangular through-hole along x: a concave, see-through object."""
    s, h = size, hole
    wall = (s - h) / 2
    parts = [
        _box([s, s, wall], [0, 0, wall / 2]),
        _box([s, s, wall], [0, 0, s - wall / 2]),
        _box([s, wall, h], [0, -(s - wall) / 2, s / 2]),
        _box([s, wall, h], [0, (s - wall) / 2, s / 2]),
    ]
    return _merge(parts)


def torus_knot(
    radius: float = 0.045, tube_radius: float = 0.009, p: int = 2, q: int = 3
) -> trimesh.Trimesh:
    """(p, q) torus knot: self-occluding thin loops."""
    t = np.linspace(0, 2 * np.pi, 96, endpoint=False)
    r = radius * (0.65 + 0.35 * np.cos(q * t))
    path = np.stack([r * np.cos(p * t), r * np.sin(p * t), radius * 0.35 * np.sin(q * t)], 1)
    return _merge([tube(path, tube_radius, sides=8, closed=True)])


def l_shape(length: float = 0.12, width: float = 0.04, height: float = 0.1) -> trimesh.Trimesh:
    """L-shaped block: the inner corner is hidden from half the viewing directions."""
    parts = [
        _box([length, width, height], [length / 2, width / 2, height / 2]),
        _box([width, length, height], [width / 2, length / 2, height / 2]),
    ]
    return _merge(parts)


def wire_rack(size: float = 0.12) -> trimesh.Trimesh:
    """Thin wire rack: a base plate with vertical rods and a top rail (thin structures)."""
    parts = [_box([size, 0.04, 0.008], [0, 0, 0.004])]
    for x in np.linspace(-0.45 * size, 0.45 * size, 5):
        parts.append(
            tube(np.array([[x, 0, 0.008], [x, 0, 0.6 * size], [x, 0, 1.1 * size]]), 0.0025, sides=6)
        )
    parts.append(
        tube(np.array([[-0.5 * size, 0, 1.1 * size], [0.5 * size, 0, 1.1 * size]]), 0.003, sides=6)
    )
    return _merge(parts)


# Name -> generator, used by the scene builder.
GENERATORS: dict[str, Callable[[], trimesh.Trimesh]] = {
    "mug": mug,
    "bowl": bowl,
    "vase": vase,
    "toy_chair": toy_chair,
    "lamp": lamp,
    "blob": blob,
    "tunnel_block": tunnel_block,
    "torus_knot": torus_knot,
    "l_shape": l_shape,
    "wire_rack": wire_rack,
}


def write_obj(mesh: trimesh.Trimesh, path) -> None:
    """Write vertices, per-vertex texture coordinates and faces as a compact Wavefront OBJ."""
    uv = getattr(mesh.visual, "uv", None)
    lines = ["# generated by sim_bridge.meshes"]
    lines += [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in mesh.vertices]
    if uv is not None:
        lines += [f"vt {a:.4f} {b:.4f}" for a, b in uv]
        lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in mesh.faces + 1]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in mesh.faces + 1]
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
