"""How the mission manager keeps in step with the graph it drives, apart from the node's wiring.

`GraphSync`, a base of `mission_manager.MissionManager`, holds the logic over what the node's
callbacks collect: which graph nodes were restarted since the runner last caught up with them
(the launcher's counts), when a restarted node's new process reads the runner's topics and their
writers have matched it, the waits on the planner's status (a restart they depend on raises
`NodeRespawned`), and the replay of saved frames until perception has answered and the planner has
fused them. The node gives it the state its callbacks fill (under `_lock`, a condition they
notify), its discovery queries (`_list`, `_readers`, `_has_graph_readers`) and `replay`.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from area3d_bringup.episode_config import EpisodeError
from area3d_bringup.graph import GRAPH_NODES
from area3d_eval.rundir import Frame
from area3d_msgs_py import topics
from area3d_msgs_py.topics import Topic

#: the topics the mission manager writes and graph nodes read: the goals, and the camera's
#: topics onto which saved frames are replayed
RUNNER_TOPICS: dict[str, Topic] = {
    "goal": topics.GOAL,
    "color": topics.COLOR,
    "depth": topics.DEPTH,
    "info": topics.CAMERA_INFO,
    "pose": topics.POSE,
}
#: the parts of a captured frame (the camera's topics, read back by the mission manager too)
CAMERA_PARTS = ("color", "depth", "info", "pose")
# Readers each runner topic has once the graph is up (the mission manager's own included):
# volatile topics drop what is published before a reader has matched, so goals and replayed
# frames wait.
EXPECTED_READERS = {
    key: len(topic.readers) + (key in CAMERA_PARTS) for key, topic in RUNNER_TOPICS.items()
}
# The runner's topics each graph node reads: once a new process of a restarted node reads them
# all, and the runner's writers have matched every reader discovery lists, it is up (a dead
# process's readers linger in discovery for a while, and a reader discovery lists a moment
# before the writer has matched it would miss what is published in between).
READS = {
    name: tuple(key for key, topic in RUNNER_TOPICS.items() if name in topic.readers)
    for name, _ in GRAPH_NODES
}
# The nodes whose restart loses fused evidence until the saved frames are replayed.
FUSION_NODES = (topics.PERCEPTION, topics.SEMANTICS, topics.PLANNER)
# A replayed frame that perception has not answered within this long is published again (its
# first copy may have gone out before a restarted node's readers had matched).
REPLAY_RESEND_S = 10.0


class NodeRespawned(RuntimeError):
    """A graph node was restarted while a step that depends on it was under way."""

    def __init__(self, name: str):
        self.name = name
        super().__init__(f"node {name!r} was restarted")


class GraphSync:
    """Restarts, readers of new processes, waits on the graph's status and replays: the mission
    logic of `MissionManager`, the node that holds the state it works on."""

    # -- restarts --------------------------------------------------------------------------------
    def respawns(self) -> dict[str, int]:
        return {} if self.launcher is None else dict(self.launcher.respawns)

    def alive_check(self) -> None:
        """Raise `NodeDied` if a node of the graph has died for good, `EpisodeError` once the
        runner's ROS context is shut down (a Ctrl-C: a wait for a frame or a plan would run to
        its timeout, with no graph nodes of the runner's own to stop it)."""
        if not self.context.ok():
            raise EpisodeError("stopped: the mission manager's ROS context was shut down")
        if self.launcher is not None:
            self.launcher.check()

    def check(self, *nodes: str) -> None:
        """Raise `NodeDied` for a node dead for good, `NodeRespawned` if one of `nodes` was
        restarted since the runner last caught up with it."""
        self.alive_check()
        counts = self.respawns()
        for name in nodes:
            if counts.get(name, 0) != self.acknowledged.get(name, 0):
                raise NodeRespawned(name)

    def restarted(self) -> list[str]:
        """Nodes restarted since the runner last caught up with them."""
        counts = self.respawns()
        return [n for n, c in counts.items() if c != self.acknowledged.get(n, 0)]

    def acknowledge(self, names: list[str]) -> None:
        counts = self.respawns()
        with self._lock:
            for name in names:
                self.acknowledged[name] = counts.get(name, 0)
            if "planner" in names:
                self.planner_status = {}  # the new planner starts from nothing

    # -- readers of the runner's topics ----------------------------------------------------------
    def _all_matched(self, key: str) -> bool:
        """The writer has matched every reader ever listed on `key`. Exact where a live count
        is not: discovery can list a new reader before the writer has matched it, and drop a
        dead process's reader before (or after) the writer unmatches it."""
        with self._lock:
            matched = self.matched_total.get(key, 0) - self.unlisted_matches.get(key, 0)
        return matched >= len(self.listed.get(key, ()))

    def note_readers(self, names: list[str]) -> None:
        """Remember the readers the graph's nodes have now (a later new one is a new process)."""
        for name in names:
            self.known_readers |= self._readers(name)
        for key in self.runner_pubs:
            self._list(key)
            listed = len(self.listed[key])
            with self._lock:
                if key not in self.unlisted_matches:
                    self.unlisted_matches[key] = max(0, self.matched_total.get(key, 0) - listed)

    def _up(self, name: str) -> bool:
        """A new process of `name` reads every topic it reads from the runner, all matched."""
        new_on = {key for key, _ in self._readers(name) - self.known_readers}
        return new_on == set(READS[name]) and all(self._all_matched(k) for k in READS[name])

    def wait_new_readers(self, names: list[str], timeout_s: float) -> None:
        """Wait until each restarted node reads the runner's topics from its new process."""
        deadline = time.monotonic() + timeout_s
        for name in names:
            while not self._up(name):
                if time.monotonic() > deadline:
                    raise TimeoutError(
                        f"restarted node {name!r} did not come up within {timeout_s:.0f} s"
                    )
                self.check(*READS)
                time.sleep(0.05)
        self.note_readers(names)

    def wait_for_readers(self, timeout_s: float) -> list[str]:
        """Wait until the camera topics have their graph readers; the topics still short of them.
        A topic has them once each graph node that reads it has a reader discovery lists, and
        the runner's writer has matched every listed reader: a reader of another program (a
        Foxglove client through the bridge, `ros2 topic echo`) never stands in for a graph node
        that has not subscribed yet, whose goal or frame would then be lost."""
        deadline = time.monotonic() + timeout_s
        while True:
            short = [key for key in self.runner_pubs if not self._has_graph_readers(key)]
            if not short or time.monotonic() > deadline:
                return short
            self.alive_check()
            time.sleep(0.05)

    # -- waits and replays (main thread) ---------------------------------------------------------
    def estimates_received(self) -> dict[int, dict[str, np.ndarray]]:
        """{stamp: {"depth", "confidence", "weight"}} of what perception has published so far."""
        with self._lock:
            return dict(self.estimates or {})

    def wait_until(
        self,
        predicate: Callable[[], bool],
        timeout_s: float,
        interrupted_by: tuple = FUSION_NODES,
    ) -> bool:
        """Wait for `predicate` (lock held while it runs); a restart of `interrupted_by` raises:
        what the wait counts on may never come without the replay that follows a restart."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while not predicate():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._lock.wait(min(remaining, 0.1))
                self.check(*interrupted_by)
        return True

    def wait_fused(self, count: int, timeout_s: float, key: str = "frames_fused") -> bool:
        """Wait until the planner reports at least `count` fused frames (or semantic maps, by `key`)."""
        return self.wait_until(lambda: int(self.planner_status.get(key, 0)) >= count, timeout_s)

    def replay_all(self, frames: list[Frame], timeout_s: float, log: Callable[[str], None]) -> None:
        """Replay saved frames so the graph knows them (after `--resume` or a restart).

        One frame at a time, each waited for until perception has answered it: parts of a later
        frame never overtake an earlier one, however far apart the saved stamps are. Then wait
        until the planner has fused every one; if it has not within `REPLAY_RESEND_S`, replay
        them all again (a restarted planner's reader can be listed by discovery a moment before
        the runner's writer has matched it; the planner fuses each stamp once, so frames it
        already has change nothing). Any restart meanwhile raises `NodeRespawned`: the caller
        starts over."""
        deadline = None
        while True:
            for i, frame in enumerate(frames):
                self._replay_one(i, frame, timeout_s, log)
            deadline = deadline or time.monotonic() + timeout_s
            if self.wait_until(
                lambda: int(self.planner_status.get("frames_fused", 0)) >= len(frames),
                min(REPLAY_RESEND_S, max(0.0, deadline - time.monotonic())),
                interrupted_by=tuple(READS),
            ):
                return
            fused = self.planner_status.get("frames_fused", 0)
            if time.monotonic() >= deadline:
                log(
                    f"[mission_manager] the planner has fused {fused} of {len(frames)} replayed "
                    f"frames after {timeout_s:.0f} s; going on"
                )
                return
            log(
                f"[mission_manager] the planner has fused {fused} of {len(frames)} replayed "
                "frames; replaying them again"
            )

    def _replay_one(
        self, index: int, frame: Frame, timeout_s: float, log: Callable[[str], None]
    ) -> None:
        """Replay one frame and wait until perception has answered it (publishing it again every
        `REPLAY_RESEND_S`: its first copy may have gone out before a new reader matched)."""
        deadline = time.monotonic() + timeout_s
        while True:
            seen = self.perceived.get(frame.stamp_ns, 0)
            self.replay(frame)
            if self.wait_until(
                lambda n=seen: self.perceived.get(frame.stamp_ns, 0) > n,
                min(REPLAY_RESEND_S, max(0.0, deadline - time.monotonic())),
                interrupted_by=tuple(READS),
            ):
                return
            if time.monotonic() >= deadline:
                log(
                    f"[mission_manager] replayed frame {index} (stamp {frame.stamp_ns}) not "
                    f"processed by perception after {timeout_s:.0f} s; going on"
                )
                return
