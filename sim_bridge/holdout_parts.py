"""What the hold-out scene writers share: a checked seed, a folder without a sidecar, seeded
lights, objects placed apart on a surface, plain materials, turning a whole set, a bottle."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim_bridge import meshes
from sim_bridge.mjcf import Mjcf

OBJECT_GAP = 0.04  # metres between the footprints of neighbouring objects


def seeded_rng(seed: int) -> np.random.Generator:
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed: got {seed!r}, expected a non-negative integer")
    return np.random.default_rng(int(seed))


def lights(rng: np.random.Generator, specular: float = 0.1) -> list[str]:
    """Two directional lights (a key light from a seeded direction above, with `specular`, a
    weaker fill light from the other side), no shadows; the model's headlight adds only its
    ambient term when rendered."""
    az = rng.uniform(0, 2 * np.pi)
    key = np.array([np.cos(az), np.sin(az), -1.6])
    fill = np.array([-np.cos(az + 0.6), -np.sin(az + 0.6), -0.8])
    return [
        f'<light name="key" directional="true" pos="0 0 4" dir="{vec3(key)}" diffuse="0.55 0.55 0.55" specular="{specular} {specular} {specular}" castshadow="false"/>',
        f'<light name="fill" directional="true" pos="0 0 4" dir="{vec3(fill)}" diffuse="0.25 0.25 0.25" specular="0 0 0" castshadow="false"/>',
    ]


def vec3(x) -> str:
    return " ".join(f"{float(a):.4f}" for a in x)


def place_apart(
    rng: np.random.Generator, radii: np.ndarray, lo: np.ndarray, hi: np.ndarray, keepout: list
) -> np.ndarray:
    """(N, 2) positions in the box [lo, hi] for discs of `radii` (N,) that overlap neither each other
    nor the keep-out boxes [(lo (2,), hi (2,)), ...] (rejection sampling, 200 tries each)."""
    out = []
    for r in radii:
        tries = rng.uniform(lo + r, hi - r, (200, 2))
        ok = np.ones(len(tries), dtype=bool)
        for k_lo, k_hi in keepout:
            nearest = np.clip(tries, k_lo, k_hi)
            ok &= np.linalg.norm(tries - nearest, axis=1) > r + OBJECT_GAP
        for p, q in out:
            ok &= np.linalg.norm(tries - p, axis=1) > r + q + OBJECT_GAP
        if not ok.any():
            raise RuntimeError(f"no free place for an object of radius {r:.3f} m")
        out.append((tries[np.argmax(ok)], r))
    return np.array([p for p, _ in out])


def plain_material(doc: Mjcf, name: str, rgb, specular=0.1, shininess=0.3, reflectance=0.0) -> str:
    """A material of one uniform colour with no texture (nothing for stereo to match on)."""
    if name not in doc.textures:
        rgba = " ".join(f"{c / 255:.3f}" for c in rgb) + " 1"
        doc.assets.append(
            f'<material name="{name}" rgba="{rgba}" specular="{specular}" '
            f'shininess="{shininess}" reflectance="{reflectance}"/>'
        )
        doc.textures.add(name)
    return name


def turn_all(doc: Mjcf, yaw: float) -> None:
    """Put everything in `doc` so far into one body turned by `yaw` (radians) about z."""
    doc.bodies = [f'<body name="turned" euler="0 0 {yaw:.6f}">', *doc.bodies, "</body>"]


def bottle_mesh():
    """A closed wine-bottle-like surface of revolution (body, shoulder, neck), 0.26 m tall."""
    z = np.array([0.0, 0.0, 0.17, 0.2, 0.215, 0.25, 0.26, 0.26])
    r = np.array([0.0, 0.035, 0.035, 0.022, 0.013, 0.013, 0.014, 0.0])
    return meshes._merge([meshes.revolve(np.stack([r, z], 1), sections=24)])


def scene_folder(folder: Path) -> Path:
    folder = Path(folder)
    for sidecar in (folder / "scene.json", *folder.glob("*.json")):
        if sidecar.is_file():
            raise ValueError(
                f"folder: got {str(folder)!r}, which holds {sidecar.name}; expected a folder without "
                "a sidecar JSON (load_scene would read it instead of deriving the metadata)"
            )
    folder.mkdir(parents=True, exist_ok=True)
    return folder
