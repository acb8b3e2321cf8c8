"""One episode's record of `area3d run`: its state (frames, views, timings) and its run directory.

`EpisodeRecord` checks the configuration, builds the graph's parameters (`presets.episode_specs`),
creates the run directory or takes a saved one up where it stopped (`--resume`), saves each
captured frame as it arrives, rewrites `episode.json` with everything known so far, and writes
`nodes.log` (the nodes' lines and the mission manager's own). The episode's steps over the graph,
which fill it, are `runner._Episode`'s (a subclass): its `run` sets `domain_id` and opens the log.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from area3d_bringup.episode_config import RESUMED_FIELDS, EpisodeConfig, episode_budget
from area3d_bringup.launch_description import merge
from area3d_bringup.launcher import Launcher
from area3d_bringup.mission_manager import NAME, MissionManager
from area3d_bringup.presets import episode_specs
from area3d_bringup.recorder import BagRecorder
from area3d_eval import rundir
from area3d_eval.rundir import Frame
from area3d_msgs_py import topics
from area3d_msgs_py.errors import InputError


class EpisodeRecord:
    """One episode's state (frames, views, timings) and its run directory."""

    def __init__(self, config: EpisodeConfig, resume: Path | None) -> None:
        from sim_bridge.scenes import load_scene

        config.validate()
        self.config = config
        self.scene = load_scene(config.scene)
        self.budget = episode_budget(self.scene, config.budget)
        self.timings: dict[str, float] = {}
        self.views: list[dict] = []
        self.frames: list[Frame] = []
        self.recorded: dict[str, int] = {}  # messages recorded before a resume, per topic
        self.stopped_early = ""  # why this run of the episode ended before the budget, if it did
        if resume is not None:
            self._resume(Path(resume))
            self.specs = self._resumed_specs()
        else:
            # the parameters are checked before the run directory is made: a run refused for a
            # parameter leaves nothing behind
            self.specs = self._specs()
            name = (
                config.run_name
                or f"{self.scene.name}_{config.policy}_s{config.seed}_{time.strftime('%Y%m%d-%H%M%S')}"
            )
            rundir.check_output_dir(config.out_dir, config.min_free_mb)
            self.run_dir = Path(config.out_dir) / name
            self.run_dir.mkdir(parents=True, exist_ok=False)
        self.n_init = len(self.scene.initial_views)
        semantics = next(spec for spec in self.specs if spec.name == topics.SEMANTICS).parameters
        self.with_semantics = semantics.get("backend", "heuristic") != "none"
        # a graph started elsewhere may run without it (found out at its reset)
        self.with_reconstruction = True
        self.recorder: BagRecorder | None = None
        self.launcher: Launcher | None = None
        self.manager: MissionManager | None = None
        self.task = None  # the progress bar's task

    def _specs(self) -> list:
        """The graph's node specs for this episode (ValueError naming a refused parameter)."""
        config = self.config
        rundir.check_depth_source(config.depth_source)
        camera: dict = {"readers.all": [NAME]}
        if self.frames:  # resumed: the camera's noise goes on after the saved frames' captures
            camera["noise_skip"] = len(self.frames)
        return episode_specs(
            config.scene,
            config.policy,
            config.seed,
            self.budget,
            config.mode,
            merge({"sim_bridge": camera}, config.overrides),
            config.params_file,
        )

    def _resume(self, run_dir: Path) -> None:
        """Take the saved episode of `run_dir` up where it stopped."""
        from sim_bridge.scenes import load_scene

        config = self.config
        episode_path = run_dir / rundir.EPISODE_FILE
        if not episode_path.is_file():
            raise FileNotFoundError(
                f"resume: got {str(run_dir)!r}, expected a run directory with episode.json"
            )
        rundir.check_output_dir(run_dir, config.min_free_mb)
        saved = rundir.read_json_object(episode_path, "the episode.json a run writes")
        for key in ("scene", "policy", "mode", "seed", "budget", "views"):
            if key not in saved:
                raise InputError(f"{episode_path}: {key}", "missing", "the run's own")
        _check_given(config, saved)
        config.scene, config.policy, config.mode = saved["scene"], saved["policy"], saved["mode"]
        config.seed, self.budget = saved["seed"], saved["budget"]
        config.depth_source = saved.get("depth_source", config.depth_source)
        self.scene = load_scene(config.scene)
        self.run_dir = run_dir
        self.views = saved["views"]
        self.frames = [
            rundir.read_frame(rundir.frame_path(run_dir, v["index"])) for v in self.views
        ]
        self.timings = saved.get("timings_s", {})
        self.recorded = dict(saved.get("recorded", {}))
        # every node's parameters as the run began ({} from a run that did not save them)
        self.saved_parameters: dict[str, dict] = dict(saved.get("config") or {})

    def _resumed_specs(self) -> list:
        """The graph's node specs of a resumed run: each node with the parameters the run began
        with (episode.json's `config`), the camera's noise going on after the saved captures. A
        parameter given now (`-p`, `--camera`) with another value than the run's own, or a
        parameter file, is refused by name: the rest of the run would not be the run it was."""
        saved = self.saved_parameters
        if not saved:  # a run directory from before the parameters were saved: as given now
            return self._specs()
        if self.config.params_file is not None:
            raise InputError(
                "--params",
                str(self.config.params_file),
                "none with --resume (a resumed run keeps the parameters it began with, "
                "episode.json's config)",
            )
        for node, parameters in self.config.overrides.items():
            own = saved.get(node, {})
            for key, value in parameters.items():
                if key not in own or own[key] != value:
                    theirs = repr(own[key]) if key in own else "the node's default (not set)"
                    raise InputError(
                        f"{node}.{key} (-p, --camera)",
                        value,
                        f"the resumed run's own {theirs} (a run goes on with the parameters it "
                        "began with: leave it out)",
                    )
        specs = self._specs()
        for spec in specs:
            if spec.name in saved:
                resumed = {k: v for k, v in saved[spec.name].items() if k != "noise_skip"}
                for key in ("noise_skip", "readers.all"):  # this run's, not the saved one's
                    if key in spec.parameters:
                        resumed[key] = spec.parameters[key]
                spec.parameters = resumed
        return specs

    # -- the run directory ----------------------------------------------------------------------
    def save(self) -> None:
        """Rewrite episode.json with everything known so far."""
        from sim_bridge.scenes import scene_reference

        counts = dict(self.recorded)
        if self.recorder is not None:
            for topic, n in self.recorder.counts.items():
                counts[topic] = counts.get(topic, 0) + n
        config = self.config
        rundir.write_episode(
            self.run_dir,
            {
                "scene": scene_reference(self.scene),  # found again from any directory
                "policy": config.policy,
                "seed": config.seed,
                "budget": self.budget,
                "level": self.scene.level,
                "mode": config.mode,
                "depth_source": config.depth_source,
                "views": self.views,
                "timings_s": self.timings,
                "config": {spec.name: spec.parameters for spec in self.specs},
                "ros": {"domain_id": self.domain_id, "namespace": config.namespace},
                "recorded": counts,
                "respawns": dict(self.launcher.respawns) if self.launcher else {},
                "planner_status": self.manager.planner_status if self.manager else {},
                "semantics": self.manager.semantics if self.manager else {},
                "stopped_early": self.stopped_early,  # empty when the budget was spent
            },
        )

    def _kept(self) -> str:
        return f"kept {len(self.frames)} captured views in {self.run_dir}; "

    def _go_on(self) -> str:
        """How to go on after a run that stopped: --resume where views were captured; where
        none was (a node that could not start: a backend's weights missing), nothing to resume."""
        if not self.frames and getattr(self, "interrupted", False):
            return "no view was captured before the stop; run the command again"
        if not self.frames:
            log = self.run_dir / "nodes.log"
            return f"no view was captured (the nodes' output: {log}); fix the cause and run again"
        return f"{self._kept()}continue with --resume {self.run_dir}"

    def add_time(self, stage: str, seconds: float) -> None:
        self.timings[stage] = self.timings.get(stage, 0.0) + seconds

    def log(self, line: str) -> None:
        """A line of the mission manager's in nodes.log."""
        with self._log_lock:
            self._log_file.write(f"[{NAME}] {line}\n")
            self._log_file.flush()

    def _log_sink(self, line: str) -> None:
        with self._log_lock:
            self._log_file.write(line + "\n")
            self._log_file.flush()

    def keep(self, frame: Frame, kind: str, stage_times: dict, progress: Any) -> None:
        """Save a captured frame and its view, and show it."""
        index = len(self.frames)
        rundir.write_frame(self.run_dir, index, *frame, stamp_ns=frame.stamp_ns)
        self.frames.append(frame)
        self.views.append(
            {
                "index": index,
                "stamp_ns": frame.stamp_ns,
                "T_world_cam": frame.T_world_cam.tolist(),
                "kind": kind,
                "stage_times_s": stage_times,
            }
        )
        self.save()
        if progress is not None:
            metric = self.manager.planner_status.get("uncertainty_total")
            extra = f" | U={metric:.1f}" if isinstance(metric, int | float) else ""
            progress.update(
                self.task,
                completed=len(self.frames),
                description=f"{self.scene.name} / {self.config.policy}: view "
                f"{len(self.frames)}/{self.budget} ({kind}){extra}",
            )


def _check_given(config: EpisodeConfig, saved: dict) -> None:
    """Refuse a run option the user gave that differs from the resumed run's own (it would be
    ignored: the run goes on as it began)."""
    from sim_bridge.scenes import load_scene, scene_reference

    def _scene_key(scene) -> str:
        reference = scene_reference(scene)
        return reference if reference == scene.name else str(Path(reference).resolve())

    for key in RESUMED_FIELDS:
        if key not in config.given:
            continue
        ours = getattr(config, key)
        theirs = saved.get(key, rundir.Episode.depth_source if key == "depth_source" else None)
        if key == "scene":  # a bundled scene by its name, any other by its file
            same = _scene_key(load_scene(ours)) == _scene_key(load_scene(theirs))
        else:
            same = ours == theirs
        if not same:
            raise InputError(
                f"--{key.replace('_', '-')}",
                ours,
                f"the resumed run's own {theirs!r} (a run goes on with its own "
                + ", ".join(f.replace("_", " ") for f in RESUMED_FIELDS)
                + ": leave the option out)",
            )
