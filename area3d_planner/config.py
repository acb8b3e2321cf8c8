"""The planner's configuration: every parameter with its default and description
(`PlannerConfig`; the paper's settings per level: `levels.py`), and the grid and planning context
the configuration describes. No state: `server.py` builds the planner from it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.grid import GridSpec
from area3d_msgs_py.param_fields import described
from area3d_planner.candidates import VisibilityParams
from area3d_planner.context import PlanningContext
from area3d_planner.fusion import GAIN_RULES, GEOMETRIC_RULES, OCCUPANCY_RULES, FusedGrid
from area3d_planner.greedy import DECAY_REGIONS, GreedyParams
from area3d_planner.levels import LEVEL_DEFAULTS, LEVELS, level_defaults_text
from area3d_planner.policies import POLICIES, make_policy

MODES = ("batch", "closed_loop")


def _xyz(value: tuple) -> str | None:
    return None if len(value) == 3 else "3 numbers [x, y, z] in metres"


def _positive(value: tuple) -> str | None:
    return None if len(value) > 0 and min(value) > 0 else "one or more numbers > 0"


def _elevations(value: tuple) -> str | None:
    ok = len(value) > 0 and all(-90.0 < float(v) < 90.0 for v in value)
    return None if ok else "one or more angles in (-90, 90) degrees"


@dataclass
class PlannerConfig:
    """All planner parameters; defaults are the paper's where it fixes them.

    The planner knows only what a robot has: its frames, their poses, the fused map, the region
    of interest (`roi_min`/`roi_max`) and the workspace box the camera may move in.
    """

    workspace_min: tuple = described(
        (-1.0, -1.0, 0.0), "lower corner [x, y, z] of the box the camera may move in", "metres",
        check=_xyz,
    )  # fmt: skip
    workspace_max: tuple = described(
        (1.0, 1.0, 1.5), "upper corner [x, y, z] of the box the camera may move in", "metres",
        check=_xyz,
    )  # fmt: skip
    roi_min: tuple = described(
        (-0.3, -0.3, 0.0), "lower corner [x, y, z] of the region of interest to reconstruct",
        "metres", check=_xyz,
    )  # fmt: skip
    roi_max: tuple = described(
        (0.3, 0.3, 0.5), "upper corner [x, y, z] of the region of interest to reconstruct",
        "metres", check=_xyz,
    )  # fmt: skip
    level: str = described(
        "auto",
        "object: candidate views on shells around the region; room: the camera works inside it; "
        "auto: room when the workspace lies inside the region (grown by 10 %), object otherwise",
        choices=LEVELS,
    )
    voxel_size: float = described(
        0.0,
        "voxel edge of the fused grid; 0 = the level's "
        f"({level_defaults_text('voxel_size')}), coarser where the grid would exceed voxel_budget",
        "metres",
        (0.0, 1.0),
    )
    voxel_budget: int = described(
        4_000_000, "most voxels the grid may hold", "voxels", (1000, 2**31 - 1)
    )
    map_margin: float = described(
        0.1, "mapped around the region of interest (object level; rooms map the workspace too)",
        "metres", (0.0, 10.0),
    )  # fmt: skip
    gamma: float = described(
        -1.0,
        "global weight every voxel starts from, so unexplored space stays attractive; < 0 = the "
        f"level's (paper, supplement: {level_defaults_text('gamma')})",
        "",
        (-1.0, 10.0),
    )
    eta: float = described(
        0.3, "frustum decay u <- (1 - eta) u after a view is chosen (paper: 0.3)", "", (0.0, 1.0)
    )
    decay: str = described(
        "frustum",
        "what a chosen view decays: every voxel in its frustum (the paper) or only those it sees",
        choices=DECAY_REGIONS,
    )
    semantic_weight: float = described(
        1.0, "weight of U_sem in the fused uncertainty; 0 = the w/o VLM ablation", "", (0.0, 100.0)
    )
    unobserved_uncertainty: float = described(
        1.0, "geometric uncertainty of a voxel no view has observed (DESIGN.md: the maximum)", "",
        (0.0, 10.0),
    )  # fmt: skip
    unobserved_reach: float = described(
        0.15,
        "an unknown voxel farther than this from every occupied voxel is probably air: it holds "
        "unobserved_far_weight times unobserved_uncertainty (0 with unobserved_far_weight 1: "
        "every unknown voxel holds it all)",
        "m",
        (0.0, 10.0),
    )
    unobserved_far_weight: float = described(
        -1.0,
        "... the share of unobserved_uncertainty an unknown voxel beyond unobserved_reach holds; "
        f"-1 = the level's ({level_defaults_text('unobserved_far_weight')}: a room is explored)",
        "",
        (-1.0, 1.0),
    )
    unobserved_reach_confidence: float = described(
        0.0,
        "... an occupied voxel counts for unobserved_reach once two frames hit it or one with at "
        "least this confidence (a lone uncertain match in the air, as stereo makes on periodic "
        "texture, does not; 0: every occupied voxel counts)",
        "confidence in [0, 1]",
        (0.0, 1.0),
    )
    geometric_rule: str = described(
        "product",
        "how observations lower a voxel's geometric uncertainty: each by its confidence "
        "(product) or 1 - their mean confidence (mean)",
        choices=GEOMETRIC_RULES,
    )
    occupancy_rule: str = described(
        "hits",
        "what a hit adds to a voxel's occupancy: one observation (hits, as OctoMap) or one "
        "weighted by the frame's confidence in it (confidence: a low-confidence match in empty "
        "air is undone by the next ray through it)",
        choices=OCCUPANCY_RULES,
    )
    carve_min_confidence: float = described(
        0.0,
        "a depth below this confidence marks its voxel but carves no free space in front of it "
        "(a depth at confidence 0 never carves)",
        "confidence in [0, 1]",
        (0.0, 1.0),
    )
    max_confidence: float = described(
        0.9,
        "most confidence one observation counts with (0.9: it lowers a voxel's uncertainty at "
        "most 10-fold)",
        "",
        (0.0, 1.0),
    )
    uniform_confidence: bool = described(
        False,
        "every pixel with depth counts with confidence 1, whatever perception says: the w/o "
        "feed-forward ablation, taken here so that perception's output and the reconstruction "
        "stay those of every other policy",
    )
    gain_rule: str = described(
        "removable",
        "what a view is worth: the uncertainty it is predicted to remove (removable: what a "
        "voxel holds times the share a new direction can still resolve, FusedGrid.achievability) "
        "or what the voxels it sees hold (held, the paper's utility)",
        choices=GAIN_RULES,
    )
    retry_gain: float = described(
        0.25,
        "after each distinct direction a voxel was observed from without being pinned down, the "
        "share of its uncertainty a new direction is expected to resolve is multiplied by this",
        "",
        (0.0, 1.0),
    )
    hard_min_directions: int = described(
        3, "a region voxel observed from at least this many distinct directions ...", "directions",
        (1, 20),
    )  # fmt: skip
    hard_max_confidence: float = described(
        0.3,
        "... whose best confidence stayed below this is a hard voxel (reported, not chased)",
        "",
        (0.0, 1.0),
    )
    clearance: float = described(
        0.05, "least distance from a camera centre to an occupied voxel", "metres", (0.0, 10.0)
    )
    seed_spacing: float = described(
        0.5, "room level: spacing of the lattice of camera positions", "metres", (0.01, 10.0)
    )
    shell_scales: tuple = described(
        (0.7, 0.85, 1.0),
        "object level: radii of the candidate shells, times the working distance of the initial "
        "views (no farther: depth from a camera is less precise, and colour coarser, with range)",
        check=_positive,
    )
    shell_elevations_deg: tuple = described(
        (0.0, 12.0, 25.0, 38.0, 52.0, 66.0, 80.0),
        "object level: elevations of the rings of each shell above the region centre's height "
        "(a robot that cannot reach low or high leaves those out)",
        "degrees",
        check=_elevations,
    )
    fan_deg: float = described(
        20.0,
        "object level: orientations within +- this around looking at the region",
        "degrees",
        (0.0, 90.0),
    )
    yaw_bins: int = described(12, "room level: orientations around the vertical", "count", (1, 360))
    pitch_bins: int = described(4, "room level: elevations per orientation", "count", (1, 90))
    face_res: int = described(
        0,
        f"edge of each face of the cube-map z-buffer; 0 = the level's ({level_defaults_text('face_res')})",
        "pixels",
        (0, 4096),
    )
    pixels_per_voxel: float = described(
        0.0,
        "a voxel seen over this many image pixels counts as fully observed; 0 = the level's "
        f"({level_defaults_text('pixels_per_voxel')})",
        "pixels",
        (0.0, 1e4),
    )
    unknown_occludes: bool = described(
        True, "a view sees up to the first layer that is not known free (occupied or unknown)"
    )
    unknown_above_occludes: bool = described(
        False,
        "object level: unknown space over the region (above its top, within its footprint) "
        "hides what lies below it too (off: a view from above sees the region through it)",
    )
    unknown_see_through: float = described(
        0.0,
        "with unknown_occludes: a view sees this far into unknown space behind the boundary of "
        "carved space and counts what it sees there (0: the boundary layer only)",
        "m",
        (0.0, 10.0),
    )
    incidence: bool = described(
        False, "a surface seen at a grazing angle counts by its cosine (off: no gain measured)"
    )
    range_profile: bool = described(
        True,
        "a voxel counts in a view by the confidence the depth backend has reached at that range "
        "so far, relative to its best range (FusedGrid.range_profile)",
    )
    repeat_gain: float = described(
        0.25,
        "a voxel seen again from a direction it was already observed from (bins about 45 degrees "
        "wide) counts this share of a new observation",
        "",
        (0.0, 1.0),
    )
    hfov_deg: float = described(
        90.0,
        "horizontal field of view of the candidate views (paper: 90) until a frame is fused; "
        "then the camera's, from its CameraInfo (2 atan(width / 2 fx))",
        "degrees",
        (1.0, 179.0),
    )
    max_range: float = described(
        5.0, "sensing range of the candidate views and of fusion (paper: 5)", "metres",
        (0.01, 1000.0),
    )  # fmt: skip
    min_range: float = described(
        0.0,
        "the camera measures nothing nearer (a structured-light or active-stereo camera's "
        "minimum range): no candidate view is placed nearer than this to geometry the map "
        "holds, and nothing nearer counts as seen (0: only clearance and a 5 cm near plane)",
        "metres",
        (0.0, 100.0),
    )
    width: int = described(
        640, "image width of the candidate views until a frame is fused (then the camera's)",
        "pixels", (8, 8192),
    )  # fmt: skip
    height: int = described(
        480, "image height of the candidate views until a frame is fused (then the camera's)",
        "pixels", (8, 8192),
    )  # fmt: skip
    w_dist: float = described(
        0.0,
        "distance prior: a candidate's score falls by this much per metre from the current pose "
        "(0 = off)",
        "per metre",
        (0.0, 1000.0),
    )
    range_sigma: float = described(
        0.0,
        "range prior: candidates off the views' working distance d0 score exp(-((d - d0) / "
        "(range_sigma d0))^2 / 2) (0 = off)",
        "fraction of d0",
        (0.0, 100.0),
    )
    nms_radius: float = described(
        0.1, "candidates this close to a chosen view, looking alike, are ruled out", "metres",
        (0.0, 10.0),
    )  # fmt: skip
    nms_angle_deg: float = described(
        30.0, "... looking within this angle of it", "degrees", (0.0, 180.0)
    )
    nms_centre_angle_deg: float = described(
        0.0,
        "object level: a view taken also rules out candidates within this angle of its direction "
        "from the region centre, at any range (0 = off)",
        "degrees",
        (0.0, 180.0),
    )
    coverage_below: float = described(
        0.05,
        "object level, one view per request: once the best view's gain falls below this share "
        "of the first planned view's, the view taken is, of those with half the best gain or "
        "more, the one farthest in direction from every captured view (0 = off)",
        "fraction",
        (0.0, 1.0),
    )
    carve_stride: int = described(
        2, "free space is carved along every n-th pixel row and column", "pixels", (1, 64)
    )
    policy: str = described("area3d", "next-best-view policy", choices=tuple(sorted(POLICIES)))
    mode: str = described(
        "batch",
        "closed_loop: re-plan after each view; batch: all views at once (paper)",
        choices=MODES,
    )
    pipeline_masks: bool = described(
        True,
        "closed loop: each request after the first plans from the visibility masks of the map "
        "at the previous request's frame (rebuilt while the camera moved) instead of waiting "
        "for the rebuild of its own frame; the uncertainty field is the current one, and "
        "candidate positions the newer frames show too close to geometry are left out. The "
        "first request, batch requests and a request from the same frame again wait for masks "
        "of their frame; with mask_lag_s > 0 (a streaming camera) that rule applies instead",
    )
    budget: int = described(
        0,
        f"total views, initial ones included; 0 = the paper's T ({level_defaults_text('budget')}). It counts "
        "the initial views and the views handed out, never the frames a streaming camera sends "
        "in between (those are fused: evidence, not views)",
        "views",
        (0, 2**31 - 1),
    )
    initial_views: int = described(
        0,
        "the initial views the budget counts: the frames fused before the first request, at most "
        f"this many; 0 = the paper's |O_0| ({level_defaults_text('initial_views')})",
        "views",
        (0, 2**31 - 1),
    )
    seed: int = described(
        0, "seed of the policies' random draws (random, sampled seeds)", "", (0, 2**31 - 1)
    )
    frame_cache: int = described(
        64, "frames kept for semantic maps that arrive after their frame", "frames", (1, 100_000)
    )

    def validate(self) -> None:
        if not (0.0 <= self.min_range < self.max_range):
            raise InputError("min_range", self.min_range, f"[0, max_range={self.max_range}) metres")
        if self.mode not in MODES:
            raise InputError("mode", self.mode, f"one of {', '.join(MODES)}")
        if self.level not in LEVELS:
            raise InputError("level", self.level, f"one of {', '.join(LEVELS)}")
        make_policy(self.policy)
        if int(self.budget) < 0:
            raise InputError(
                "budget",
                self.budget,
                "an integer >= 1 (total views, initial ones included; 0 = the paper's)",
            )
        if int(self.voxel_budget) < 1000:
            raise InputError("voxel_budget", self.voxel_budget, "an integer >= 1000 voxels")
        if not (np.isfinite(self.map_margin) and self.map_margin >= 0):
            raise InputError("map_margin", self.map_margin, "a value >= 0 metres")
        if not (np.isfinite(self.pixels_per_voxel) and self.pixels_per_voxel >= 0):
            raise InputError(
                "pixels_per_voxel", self.pixels_per_voxel, "a value > 0 (0 = the level's)"
            )
        if not (np.isfinite(self.voxel_size) and self.voxel_size >= 0):
            raise InputError("voxel_size", self.voxel_size, "a value >= 0 metres (0 = automatic)")
        for name in ("workspace", "roi"):
            lo = np.asarray(getattr(self, f"{name}_min"), float)
            hi = np.asarray(getattr(self, f"{name}_max"), float)
            if (
                lo.shape != (3,)
                or hi.shape != (3,)
                or not np.all(np.isfinite(hi - lo))
                or not np.all(hi > lo)
            ):
                raise InputError(
                    f"{name}_min/{name}_max", [lo.tolist(), hi.tolist()], "min < max on every axis"
                )

    def resolved_level(self) -> str:
        """ "object" or "room": the configured level, or the automatic rule for "auto"."""
        if self.level != "auto":
            return self.level
        roi_lo, roi_hi = np.asarray(self.roi_min, float), np.asarray(self.roi_max, float)
        grow = 0.1 * (roi_hi - roi_lo)
        ws_lo, ws_hi = np.asarray(self.workspace_min, float), np.asarray(self.workspace_max, float)
        inside = np.all(ws_lo >= roi_lo - grow) and np.all(ws_hi <= roi_hi + grow)
        return "room" if inside else "object"

    def grid_spec(self) -> GridSpec:
        """The voxel grid: the ROI grown by map_margin (room level: and the workspace, where the
        camera moves); the level's voxel size, or the smallest multiple of 1 mm that keeps the grid
        within voxel_budget; origin half a voxel below the ROI's corner, so planes at the box faces
        (a table top, a floor) lie mid-voxel and not on a voxel boundary."""
        roi_lo, roi_hi = np.asarray(self.roi_min, float), np.asarray(self.roi_max, float)
        lo, hi = roi_lo - self.map_margin, roi_hi + self.map_margin
        if self.resolved_level() == "room":
            lo = np.minimum(lo, np.asarray(self.workspace_min, float))
            hi = np.maximum(hi, np.asarray(self.workspace_max, float))
        voxel = self.voxel_size or LEVEL_DEFAULTS[self.resolved_level()]["voxel_size"]
        while True:
            # whole voxels from the ROI corner outwards, so the ROI faces stay mid-voxel
            start = roi_lo - (np.ceil((roi_lo - lo) / voxel - 1e-9) + 0.5) * voxel
            spec = GridSpec.from_bounds(start, hi + 0.5 * voxel, voxel)
            if spec.num_voxels <= int(self.voxel_budget):
                return spec
            voxel = np.ceil(1000 * voxel * (spec.num_voxels / self.voxel_budget) ** (1 / 3)) / 1000

    def resolved_gamma(self) -> float:
        return self.gamma if self.gamma >= 0 else LEVEL_DEFAULTS[self.resolved_level()]["gamma"]

    def resolved_unobserved_far_weight(self) -> float:
        w = self.unobserved_far_weight
        return w if w >= 0 else LEVEL_DEFAULTS[self.resolved_level()]["unobserved_far_weight"]

    def resolved_budget(self) -> int:
        return int(self.budget) or LEVEL_DEFAULTS[self.resolved_level()]["budget"]

    def resolved_initial_views(self) -> int:
        return int(self.initial_views) or LEVEL_DEFAULTS[self.resolved_level()]["initial_views"]

    def fused_grid(self) -> FusedGrid:
        """An empty evidence grid of this configuration."""
        return FusedGrid(
            self.grid_spec(),
            self.roi_min,
            self.roi_max,
            self.resolved_gamma(),
            self.unobserved_uncertainty,
            self.semantic_weight,
            self.geometric_rule,
            self.max_confidence,
            self.gain_rule,
            self.retry_gain,
            self.hard_min_directions,
            self.hard_max_confidence,
            self.occupancy_rule,
            self.carve_min_confidence,
            self.unobserved_reach,
            self.resolved_unobserved_far_weight(),
            self.unobserved_reach_confidence,
        )

    def planning_context(self, grid: FusedGrid) -> PlanningContext:
        """The planning context of this configuration over `grid`: its workspace, candidate views
        (for the parameters' camera until a frame says otherwise) and greedy selection."""
        level = self.resolved_level()
        return PlanningContext(
            grid=grid,
            workspace_lo=np.asarray(self.workspace_min, float),
            workspace_hi=np.asarray(self.workspace_max, float),
            clearance=max(self.clearance, self.min_range),
            visibility=VisibilityParams(
                level=level,
                shell_scales=tuple(float(v) for v in self.shell_scales),
                shell_elevations_deg=tuple(float(v) for v in self.shell_elevations_deg),
                fan_deg=self.fan_deg,
                seed_spacing=self.seed_spacing,
                yaw_bins=self.yaw_bins,
                pitch_bins=self.pitch_bins,
                hfov_deg=self.hfov_deg,
                width=self.width,
                height=self.height,
                max_range=self.max_range,
                near=max(VisibilityParams.near, self.min_range),
                face_res=self.face_res or LEVEL_DEFAULTS[level]["face_res"],
                pixels_per_voxel=self.pixels_per_voxel or LEVEL_DEFAULTS[level]["pixels_per_voxel"],
                unknown_occludes=self.unknown_occludes,
                unknown_above_occludes=self.unknown_above_occludes,
                unknown_see_through=self.unknown_see_through,
                incidence=self.incidence,
                range_profile=self.range_profile,
                repeat_gain=self.repeat_gain,
            ),
            greedy=GreedyParams(
                eta=self.eta,
                w_dist=self.w_dist,
                nms_radius=self.nms_radius,
                nms_angle_deg=self.nms_angle_deg,
                nms_centre_angle_deg=self.nms_centre_angle_deg,
                range_sigma=self.range_sigma,
                decay=self.decay,
                coverage_below=self.coverage_below,
            ),
            rng_seed=self.seed,
        )
