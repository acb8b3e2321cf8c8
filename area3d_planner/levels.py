"""The planner's settings per level, where the paper distinguishes object level and scene (room)
level (`LEVEL_DEFAULTS`: |O_0|, T, gamma and ours); `config.PlannerConfig` takes a level's value
where a parameter is left at 0 (or -1)."""

from __future__ import annotations

# Where the paper distinguishes object level and scene (room) level.
LEVEL_DEFAULTS = {
    # paper: gamma, T; ours: voxel, z-buffer resolution (about half a voxel's angle at the working
    # distance: 1 cm at 0.7 m, 5 cm at 2 m)
    # and the resolution term (8 x 8 pixels per voxel: a pixel footprint of 1.25 mm at object
    # level, 6 mm at room level; chosen on the bundled scenes, planner README)
    "object": {
        "initial_views": 4,
        "voxel_size": 0.01,
        "gamma": 0.01,
        "budget": 25,
        "face_res": 256,
        "pixels_per_voxel": 64.0,
        "unobserved_far_weight": 0.25,
    },
    "room": {
        "initial_views": 15,
        "voxel_size": 0.05,
        "gamma": 0.005,
        "budget": 40,
        "face_res": 128,
        "pixels_per_voxel": 64.0,
        "unobserved_far_weight": 1.0,
    },
}
LEVELS = ("auto", "object", "room")


def paper_budget(level: str) -> int:
    """The paper's view budget T at `level` ("object" or "room"): total views, O_0 included
    (25 object level, 40 scene level)."""
    return LEVEL_DEFAULTS[level]["budget"]


def level_defaults_text(key: str) -> str:
    """The level defaults of `key`, as a description says them."""
    return ", ".join(f"{v[key]:g} {level}" for level, v in LEVEL_DEFAULTS.items())
