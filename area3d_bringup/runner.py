"""`area3d run`: one active-reconstruction episode over the node graph (`run_episode`).

It launches the graph, drives the camera through the initial views O_0, then asks the planner's
next-best-view service for views and drives the camera there until the view budget is spent.
Every captured frame is saved in the run directory as it arrives (and `episode.json` rewritten), so a
crash loses nothing and `--resume RUN_DIR` continues where the episode stopped: the saved frames are
replayed onto the camera topics for the new graph, then planning goes on with the remaining budget.

With `respawn` on, a node that dies is started again by the launcher and the episode goes on: the
step it interrupted (a capture for the camera, a plan or a wait for the planner) is retried once
the new process is up, and the graph is brought up to date from the same saved frames that
`--resume` replays, so the restarted planner fuses again everything it had fused (perception and
semantics recompute their outputs from the frames; the planner fuses each stamp once).

The episode's state and run directory are `episode_record.EpisodeRecord`'s, its parameters from
`presets.episode_specs` as the in-process path's are; the runner's node is
`mission_manager.MissionManager`.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import rclpy

from area3d_bringup.episode_config import EpisodeConfig, EpisodeError, GraphInUse
from area3d_bringup.episode_record import EpisodeRecord
from area3d_bringup.launcher import Launcher, NodeDied
from area3d_bringup.mission_manager import NAME, MissionManager
from area3d_bringup.mission_sync import READS, REPLAY_RESEND_S, NodeRespawned
from area3d_bringup.recorder import BagRecorder
from area3d_eval import rundir
from area3d_msgs_py import codecs, middleware, msgs, topics
from area3d_msgs_py.spinning import GuardedExecutor, Spinner

__all__ = ["EpisodeConfig", "EpisodeError", "run_episode"]

# How often the start looks for the planner's service (rclpy's `wait_for_service` sleeps 0.25 s
# between its looks: the episode started on average 0.12 s after the service was there).
SERVICE_POLL_S = 0.02
# A running graph without the reconstruction node: its reset is given up after this long.
OPTIONAL_RESET_S = 10.0
# A resumed episode's planner, asked again for a saved view, answers it within this (metres, and
# rotation matrix entries): the camera's pose comes back through a quaternion.
SAVED_VIEW_TOL = 1e-6


def run_episode(
    config: EpisodeConfig, resume: Path | None = None, progress: object | None = None
) -> Path:
    """Run one episode; returns the run directory (frames, episode.json, bag, grids).
    `progress`: a rich Progress to show the views on."""
    return _Episode(config, resume).run(progress)


# How long the mission manager's callbacks may take to end when the run ends, seconds.
SPINNER_STOP_S = 30.0
# After a Ctrl-C of `area3d run`, SIGINT is passed on to the nodes still running this much later.
FORWARD_SIGINT_AFTER_S = 1.0


class _Episode(EpisodeRecord):
    """One episode's steps over the graph, in the order they run, on its record."""

    def __init__(self, config: EpisodeConfig, resume: Path | None) -> None:
        super().__init__(config, resume)
        self.catching_up: set[str] = set()  # restarted nodes whose new process is not up yet
        self.replay_due = False  # a restart lost fused evidence that the saved frames give back
        # After a restart, the camera's writers may match the new process's readers only after
        # its next frame (discovery between two other processes is not for the runner to wait
        # on): the first frame after a restart is checked as fused, else replayed by the runner.
        self.check_next_capture = False
        self.held_back = 0  # saved planned views not given yet: replayed once asked again

    # -- the run --------------------------------------------------------------------------------
    def _note_sigint(self, context: Any) -> Callable[[], None]:
        """On Ctrl-C: note it (`interrupted`), pass SIGINT on to the graph's nodes (a terminal
        gives it to the whole process group; `kill -INT`, `timeout -s INT` to this process alone)
        and stop the mission manager's `context` (rclpy installs no handler for a context of
        its own), so a request in flight fails, which reads as the user's stop, not the
        planner's failure. Only in the main thread (where Python takes signals); returns what
        puts the handler back."""
        self.interrupted = False
        if threading.current_thread() is not threading.main_thread():
            return lambda: None
        previous = signal.getsignal(signal.SIGINT)

        def stop() -> None:
            launcher = getattr(self, "launcher", None)
            if launcher is not None:
                launcher.interrupt(send=False)  # no node is started again
            context.try_shutdown()
            # a terminal's Ctrl-C reached the nodes too: a second SIGINT at once would land in
            # their teardown before they ignore it; a second later only the nodes still running
            # (signalled alone: kill -INT to this process) need it, the others ignore it by then
            time.sleep(FORWARD_SIGINT_AFTER_S)
            if launcher is not None:
                launcher.interrupt()

        def noted(signum: int, frame: Any) -> None:
            self.interrupted = True  # no KeyboardInterrupt: the run ends through its errors
            # on a thread: the main thread, which runs this handler, may hold the locks these
            # take (the launcher's, the context's) at the moment the signal came
            threading.Thread(target=stop, name="sigint-stop", daemon=True).start()

        signal.signal(signal.SIGINT, noted)
        return lambda: signal.signal(signal.SIGINT, previous)

    def run(self, progress: Any) -> Path:
        config = self.config
        lease = middleware.DomainLease(config.domain_id)
        self.domain_id = lease.domain_id
        # Discovery stays on this machine unless the caller's environment says otherwise.
        discovery = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") or "LOCALHOST"
        env = middleware.graph_env(self.domain_id, config.transport, discovery)
        os.environ.update(env)  # this process's own participant: same transport and discovery
        self.domain_in_use = not lease.picked and middleware.domain_in_use(self.domain_id)
        self._log_file = (self.run_dir / rundir.LOG_FILE).open("a")
        self._log_lock = threading.Lock()
        self.recorder = BagRecorder(rundir.bag_path(self.run_dir)) if config.record else None
        t0 = time.monotonic()
        local = [spec for spec in self.specs if config.nodes is None or spec.name in config.nodes]
        self.started = {spec.name for spec in local}  # the others run already (`--nodes`)
        if config.foxglove_port is not None:
            from area3d_bringup.foxglove_bridge import bridge_spec

            local.append(bridge_spec(config.foxglove_port, config.foxglove_address))
        self.launcher = Launcher(
            local,
            self.run_dir,
            env=env,
            log_sink=self._log_sink,
            namespace=config.namespace,
            respawn=config.respawn,
            respawn_delay_s=config.respawn_delay_s,
            respawn_max_retries=config.respawn_max_retries,
        )
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=self.domain_id)
        self.manager = MissionManager(
            self.recorder,
            launcher=self.launcher,
            clock=config.clock,
            keep_estimates=config.depth_source == "estimated",
            context=context,
            namespace=config.namespace or None,
        )
        restore_sigint = self._note_sigint(context)
        executor = GuardedExecutor(context=context)
        executor.add_node(self.manager)
        spinner = Spinner(executor, name=NAME)
        where = (
            f"graph on ROS_DOMAIN_ID={self.domain_id}"
            f"{' (picked: free)' if lease.picked else ''}, namespace {config.namespace or '/'}, "
            f"transport {env[middleware.TRANSPORT_ENV]}, discovery {discovery}"
        )
        self.log(where)
        if progress is not None:  # where a user's `ros2` tools find the graph, on the console
            progress.console.print(where)
        try:
            self._start_graph(t0, progress)
            self._episode(progress)
            self.add_time("episode_total", time.monotonic() - t0)
            self.save()
        except GraphInUse:
            raise
        except (NodeDied, TimeoutError, EpisodeError) as err:
            if self.interrupted:  # Ctrl-C: the nodes and the manager were stopped by it
                self.stopped_early = ""
            self.save()
            why = "interrupted (Ctrl-C)" if self.interrupted else str(err)
            raise EpisodeError(f"{why}\n{self._go_on()}") from err
        except OSError as err:  # the disk filled up or went away mid-run
            raise EpisodeError(
                f"writing the run directory failed: {err}\n{self._kept()}free space, then "
                f"continue with --resume {self.run_dir}"
            ) from err
        finally:
            self.launcher.stop()
            # a callback still running (a grid read and recorded, on a loaded machine) must end
            # before the node is destroyed under it: destroyed after 2 s, the run once ended in
            # a segmentation fault; one that never ends leaves the node to the process's exit
            if spinner.stop(timeout_s=SPINNER_STOP_S):
                self.manager.destroy_node()
            else:
                self.log(f"the mission manager's callbacks did not end within {SPINNER_STOP_S} s")
            context.try_shutdown()
            try:
                if self.recorder is not None:
                    self.recorder.close()
                self.save()
            except OSError as err:  # a full disk: what was written before stays readable
                self.log(f"could not write the run directory at the end: {err}")
            lease.release()
            self._log_file.close()
            restore_sigint()
        return self.run_dir

    def _start_graph(self, t0: float, progress: Any) -> None:
        """Start the graph's processes and wait until the planner serves and the camera topics
        have their readers."""
        manager, config = self.manager, self.config
        if self.domain_in_use:  # a given domain: another graph's nodes would answer for ours
            manager.refuse_a_running_graph(self.started, self.domain_id)
        self.launcher.start()
        if self.interrupted:  # Ctrl-C while the nodes were being started
            self.launcher.interrupt()
            raise EpisodeError("interrupted (Ctrl-C)")
        ready = manager.client.service_is_ready
        if not self.launcher.wait_for(ready, config.startup_timeout_s, SERVICE_POLL_S):
            raise EpisodeError(
                f"the planner service {topics.SELECT_VIEWS.name} did not appear within "
                f"{config.startup_timeout_s:.0f} s"
            )
        short = manager.wait_for_readers(config.startup_timeout_s)
        if short:
            self.log(f"topics {short} have fewer readers than the graph should give them")
        manager.note_readers(list(READS))
        self._reset_graph()
        self.add_time("launch", time.monotonic() - t0)
        if progress is not None:
            self.task = progress.add_task(f"{self.scene.name} / {config.policy}", total=self.budget)
            progress.update(self.task, completed=len(self.frames))

    def _reset_graph(self) -> None:
        """A camera, planner (and semantics) this run did not start keep the noise stream, map
        (and views) of the episodes before: reset them, so that this episode starts from nothing
        and repeats as on a graph of its own (a resumed one then replays its frames)."""
        resets = [topics.CAMERA_RESET, topics.PLANNER_RESET]
        resets += [topics.SEMANTICS_RESET] * self.with_semantics
        resets += [topics.RECONSTRUCTION_RESET]
        for service in resets:
            if service.server in self.started:
                continue
            optional = service is topics.RECONSTRUCTION_RESET  # a graph may run without it
            timeout_s = self.config.startup_timeout_s
            try:
                said = self.manager.reset(
                    service, min(timeout_s, OPTIONAL_RESET_S) if optional else timeout_s
                )
            except (NodeDied, NodeRespawned):  # a node of this run's: handled as elsewhere
                raise
            except TimeoutError:
                if not optional:
                    raise
                self.log(f"no {service.server} in the running graph: {service.name} not called")
                self.with_reconstruction = False
                continue
            except RuntimeError as err:  # the service answered that it failed
                raise EpisodeError(
                    f"the graph's {service.server} could not be reset: {err}"
                ) from err
            self.log(f"{service.server} of the running graph reset: {said}")

    def _episode(self, progress: Any) -> None:
        """Replay what a resumed episode had, capture O_0, plan and capture until the budget is
        spent, then keep the last outputs of the graph."""
        config, manager = self.config, self.manager
        if self.frames:  # what an interrupted episode had already captured: the graph learns it
            t = time.monotonic()
            # the initial views now, the planned ones as the planner is asked for them again
            initial = self.frames[: self.n_init]
            self.held_back = len(self.frames) - len(initial)
            self.step(lambda: manager.replay_all(initial, config.fuse_timeout_s, self.log))
            self.add_time("replay", time.monotonic() - t)
        self._initial_views(progress)
        initial_grid = self.run_dir / rundir.GRID_INITIAL_FILE
        if manager.latest_grid is not None and not initial_grid.exists():
            rundir.write_grid(initial_grid, _grid(manager.latest_grid))
        self._planned_views(progress)
        if not self.step(lambda: self.all_fused(config.fuse_timeout_s)):
            self.log(
                f"the planner has fused {manager.planner_status.get('frames_fused', 0)} of "
                f"{len(self.frames)} frames at the end"
            )
        # Let the bag catch up with what the planner and perception published for the last frame.
        perception_depth = manager.resolve_topic_name(topics.PERCEPTION_DEPTH.name)
        self.step(
            lambda: manager.wait_until(
                lambda: manager.received.get(perception_depth, 0) >= len(self.frames), 10.0
            )
        )
        if manager.estimates is not None:
            rundir.attach_estimates(
                self.run_dir, self.frames, manager.estimates_received(), self.log
            )
        if manager.latest_grid is not None:
            rundir.write_grid(self.run_dir / rundir.GRID_FINAL_FILE, _grid(manager.latest_grid))
        self._save_maps()

    def _save_maps(self) -> None:
        """The graph's maps and live mesh into the run's `maps/` over its services (the planner's,
        and the reconstruction's once it has integrated every frame); one that fails is logged,
        the episode's results stand."""
        manager, timeout_s = self.manager, self.config.fuse_timeout_s
        folder = self.run_dir / rundir.MAPS_DIR
        folder.mkdir(exist_ok=True)
        saves = [(topics.PLANNER_SAVE_MAP, rundir.PLANNER_MAP_FILE)]
        if self.with_reconstruction:
            if not self.step(
                lambda: manager.wait_until(
                    lambda: (
                        int(manager.reconstruction_status.get("frames_integrated", 0))
                        >= len(self.frames)
                    ),
                    timeout_s,
                )
            ):
                self.log("the reconstruction has not integrated every frame; saving what it has")
            saves += [
                (topics.RECONSTRUCTION_SAVE_MAP, rundir.RECONSTRUCTION_MAP_FILE),
                (topics.RECONSTRUCTION_EXPORT_MESH, rundir.LIVE_MESH_FILE),
            ]
        for service, name in saves:
            try:
                said = self.step(
                    lambda s=service, n=name: manager.map_file(s, folder / n, timeout_s)
                )
                self.log(f"{service.name}: {said}")
            except (TimeoutError, RuntimeError) as err:
                self.log(f"{service.name} failed, {name} not saved: {err}")

    def _initial_views(self, progress: Any) -> None:
        """Capture the views of O_0 not captured yet, then wait for their semantic maps and for
        the planner to fuse them."""
        config, manager = self.config, self.manager
        remaining = self.scene.initial_views[len(self.frames) : self.n_init]
        for T in remaining if len(self.frames) < self.n_init else []:
            t = time.monotonic()
            stamp = manager.clock()  # kept if the capture is repeated
            result = self.step(lambda T=T, s=stamp: manager.capture(T, config.capture_timeout_s, s))
            self.launcher.check()
            if isinstance(result, str):
                raise EpisodeError(f"the camera refused initial view {len(self.frames)}: {result}")
            self.add_time("capture", time.monotonic() - t)
            self.keep(result, "initial", {"capture": time.monotonic() - t}, progress)
            self.captured()
        if self.with_semantics and not self.step(
            lambda: manager.wait_fused(
                self.n_init, config.plan_timeout_s, key="semantic_frames_fused"
            )
        ):
            self.log(
                f"no semantic maps for the initial views after {config.plan_timeout_s:.0f} s; "
                "planning without them"
            )
        if not self.step(lambda: manager.wait_fused(self.n_init, config.fuse_timeout_s)):
            self.log(
                f"the planner has not fused all {self.n_init} initial views after "
                f"{config.fuse_timeout_s:.0f} s; planning with what it has"
            )

    def _planned_views(self, progress: Any) -> None:
        """Ask the planner for views (one at a time in closed loop, all at once in batch) and
        capture them until the budget is spent or the planner has no view left."""
        config, manager = self.config, self.manager
        planned = len(self.frames) - self.held_back - self.n_init
        refused = 0
        to_plan = self.budget - self.n_init
        while planned < to_plan:
            t = time.monotonic()
            count = 1 if config.mode == "closed_loop" else to_plan - planned
            current = self.frames[len(self.frames) - self.held_back - 1]  # the graph's last
            poses = self.step(lambda c=count, f=current: manager.plan(f, c, config.plan_timeout_s))
            plan_s = time.monotonic() - t
            self.add_time("replay" if self.held_back else "plan", plan_s)  # asked again: replay
            self.launcher.check()
            if not poses and self.interrupted:
                raise EpisodeError("interrupted (Ctrl-C)")
            if not poses:
                self.stopped_early = rundir.stopped_early(to_plan - planned, manager.plan_message)
                self.log(f"{self.stopped_early}; stopping early")
                return
            for T in poses[: to_plan - planned]:
                if self.held_back:  # a saved view of the resumed episode: replayed, not captured
                    self._replay_saved_view(T)
                    planned += 1
                    continue
                t = time.monotonic()
                stamp = manager.clock()  # kept if the capture is repeated
                result = self.step(
                    lambda T=T, s=stamp: manager.capture(T, config.capture_timeout_s, s)
                )
                self.add_time("capture", time.monotonic() - t)
                if isinstance(result, str):
                    refused += 1
                    self.log(f"the camera refused a planned view: {result}")
                    if refused > self.budget:
                        raise EpisodeError(
                            "the camera refused more planned views than the budget; stopping"
                        )
                    continue
                planned += 1
                stage_times = {"plan": plan_s / len(poses), "capture": time.monotonic() - t}
                self.keep(result, "planned", stage_times, progress)
                self.captured()

    def _replay_saved_view(self, T: np.ndarray) -> None:
        """Replay the next saved planned view of a resumed episode, which the planner has just been
        asked for again: so the planner holds what it held when the episode was stopped (the views
        it handed out and their decay, the masks of the last request's frame, the working distance
        of the initial views), and goes on choosing the views of the episode never stopped. Every
        saved frame replayed before the first request would count as an initial view, with none
        handed out, and other views would follow."""
        index = len(self.frames) - self.held_back
        frame = self.frames[index]
        if not np.allclose(T, frame.T_world_cam, rtol=0.0, atol=SAVED_VIEW_TOL):
            self.log(
                f"the planner chose another view {index} than the saved one; replaying the saved "
                "one (the views from here may differ from those of the episode never stopped)"
            )
        timeout_s = self.config.fuse_timeout_s
        self.step(lambda: self.manager.replay_all([frame], timeout_s, self.log))
        self.held_back -= 1
        self.step(lambda: self.manager.wait_fused(index + 1, timeout_s))

    # -- restarts ---------------------------------------------------------------------------------
    def step(self, action: Callable[[], Any]) -> Any:
        """Run one episode step; a restart it depends on is caught up with and it runs again."""
        while True:
            self.recover()
            try:
                return action()
            except NodeRespawned as err:
                self.log(f"{err} during a step; repeating the step")

    def recover(self) -> None:
        """Bring restarted nodes up to date: wait for their new process, then replay every saved
        frame (not after the camera alone: it keeps no state). A restart meanwhile starts this
        over, with nothing of the earlier one forgotten."""
        manager = self.manager
        while True:
            changed = manager.restarted()
            if changed:
                self.log(f"{', '.join(changed)} restarted; bringing the graph up to date")
                manager.acknowledge(changed)
                self.catching_up.update(changed)
                self.replay_due = self.replay_due or bool(set(changed) - {topics.SIM_BRIDGE})
                self.check_next_capture = True
            if not self.catching_up and not self.replay_due:
                return
            t = time.monotonic()
            try:
                for name in sorted(self.catching_up):
                    manager.wait_new_readers([name], self.config.startup_timeout_s)
                    self.catching_up.discard(name)
                given = self.frames[: len(self.frames) - self.held_back]  # the graph's frames
                if self.replay_due and given:
                    manager.replay_all(given, self.config.fuse_timeout_s, self.log)
                    if self.with_semantics and len(self.frames) >= self.n_init:
                        self.semantic_maps_back()
                self.replay_due = False
            except NodeRespawned:
                continue
            self.add_time("recover", time.monotonic() - t)

    def all_fused(self, wait_s: float) -> bool:
        """The planner has fused every captured frame; where it has not within `wait_s`, replay
        them (it fuses each stamp once) and wait up to the fusion timeout."""
        manager = self.manager
        if manager.wait_fused(len(self.frames), wait_s):
            return True
        self.log(
            f"the planner has fused {manager.planner_status.get('frames_fused', 0)} "
            f"of {len(self.frames)} captured frames; replaying them"
        )
        manager.replay_all(self.frames, self.config.fuse_timeout_s, self.log)
        return manager.wait_fused(len(self.frames), 0.0)

    def captured(self) -> None:
        """After the first capture following a restart, make sure the graph has it."""
        if self.check_next_capture:
            self.step(lambda: self.all_fused(REPLAY_RESEND_S))
            self.check_next_capture = False

    def semantic_maps_back(self) -> None:
        """The planner holds the semantic maps of O_0 again (a restarted semantics queries the
        initial views once it has them; replay them again until it has)."""
        manager, config = self.manager, self.config
        deadline = time.monotonic() + config.plan_timeout_s
        while not manager.wait_fused(self.n_init, REPLAY_RESEND_S, key="semantic_frames_fused"):
            if time.monotonic() > deadline:
                self.log(
                    f"no semantic maps of the initial views after {config.plan_timeout_s:.0f} s; "
                    "going on without them"
                )
                return
            self.log("no semantic maps of the initial views yet; replaying them")
            manager.replay_all(self.frames[: self.n_init], config.fuse_timeout_s, self.log)


def _grid(cdr: bytes) -> np.ndarray:
    return codecs.msg_to_pointcloud(msgs.deserialize(cdr, topics.UNCERTAINTY_GRID.type_name))
