"""Soak: a camera streams 640x480 RGB-D at 10 Hz through the perception and planner nodes (real
processes) for 10 minutes or 6000 frames, while a mission manager (a process of its own,
`soak_manager`) asks for a next view every second from the newest camera pose it has seen, once
the planner has fused a frame (before, the answer would be an empty plan), until it has had an
answer at least.

Figures: frames the camera sent, published by perception and fused by the planner, and those
each node dropped and counted (`frame_accounting`: none may be lost uncounted, and at the target
rate none dropped); each node's resident memory at the start and the end of the stream (it must
stay flat);
the next-best-view round trips during fusion (planning and fusion must not block each other),
beside the closed-loop target. The frames are the scene's views rendered once and sent again
with new stamps, so rendering does not compete with the nodes for the CPU.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from area3d_bench.frame_accounting import (
    PERCEPTION_DROPS,
    dropped,
    perception_accounted,
    planner_accounted,
)

# Per request during fusion, p95: the object-level closed-loop target (planner.py).
TARGET_PLAN_P95_S = 0.3
RATE_HZ = 10.0
# The planner's setting for a streaming camera: plan from masks up to 1 s behind the request's
# frame rather than wait for a rebuild (the uncertainty field is always current).
MASK_LAG_S = 1.0
# ... and it rebuilds them at a lower CPU priority than fusion (nice +10): fusing every frame on
# time comes first
REBUILD_NICE = 10
FRAMES = 6000
DURATION_S = 600.0
SCENE = "single_object"
NODES = ("perception", "planner")
# after the stream, the mission manager is stopped once it has had an answer, or after this long
FIRST_ANSWER_WAIT_S = 180.0


def rss_mb(pid: int) -> float:
    """Resident set size of a process in MB, from /proc (Linux)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def rss_parts_mb(pid: int) -> dict[str, float]:
    """The resident set's parts in MB (Linux /proc): anonymous (the heap: the node's own data),
    shared memory (the middleware's shared-memory segments, mapped from every peer, whose pages
    count once touched) and file-backed (code, libraries)."""
    keys = {"RssAnon:": "anon", "RssShmem:": "shmem", "RssFile:": "file"}
    parts = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key = line.split(":")[0] + ":"
        if key in keys:
            parts[keys[key]] = int(line.split()[1]) / 1024.0
    return parts


@dataclass
class _Run:
    """What one soak records while it streams."""

    sent: list[int] = field(default_factory=list)  # stamps published
    latencies: list[float] = field(default_factory=list)  # request round trips, seconds
    breakdown: list[dict] = field(default_factory=list)  # the planner's split of each
    empty_plans: list[str] = field(default_factory=list)
    late: int = 0  # publishes more than one period late
    warm: tuple[int, int, int] = (0, 0, 0)  # statuses and answers before the first tenth ended
    rss_idle: dict[str, float] = field(default_factory=dict)
    rss_start: dict[str, float] = field(default_factory=dict)  # after the first tenth
    rss_end: dict[str, float] = field(default_factory=dict)
    rss_peak: dict[str, float] = field(default_factory=dict)
    rss_tenths: dict[str, list[int]] = field(default_factory=dict)  # at each tenth's end
    rss_parts_tenths: dict[str, dict[str, list[int]]] = field(default_factory=dict)
    stream_t0: float = 0.0  # time.perf_counter() at the stream's start
    stream_s: float = 0.0
    drain_s: float = 0.0
    caught_up: bool = False


def run_bench(
    frames: int = FRAMES,
    duration_s: float = DURATION_S,
    rate_hz: float = RATE_HZ,
    plan_every_s: float = 1.0,
    scene_name: str = SCENE,
    width: int = 640,
    height: int = 480,
    print_table: bool = True,
    mask_lag_s: float = MASK_LAG_S,
    rebuild_nice: int = REBUILD_NICE,
    json_out: Path | None = None,
) -> dict:
    """Stream min(frames, duration_s * rate_hz) frames; returns the figures (see module doc)."""
    from area3d_bench.frames import render_views
    from area3d_bringup.launch_description import NodeSpec, scene_parameters
    from area3d_bringup.launcher import Launcher
    from area3d_msgs_py import middleware, topics
    from area3d_msgs_py.probe import Probe

    middleware.configure()
    count = int(min(frames, round(duration_s * rate_hz)))
    scene, views = render_views(scene_name, width, height, held_out=True)
    planner = {
        **scene_parameters(scene_name)["planner"],
        "mode": "closed_loop",
        "budget": 2**31 - 1,  # every request plans; the budget never runs out
        "mask_lag_s": mask_lag_s,
        "rebuild_nice": rebuild_nice,
        "width": width,
        "height": height,
    }
    lines: list[str] = []
    run = _Run()
    with tempfile.TemporaryDirectory() as workdir, Probe("soak_camera") as probe:
        launcher = Launcher(
            [
                NodeSpec("perception", "area3d_perception.node", {}),
                NodeSpec("planner", "area3d_planner.node", planner),
            ],
            Path(workdir),
            env=middleware.graph_env(),
            log_sink=lines.append,
        )
        planner_status, perception_status = (
            probe.listen(topic.msg_type, topic.name, topic.qos())
            for topic in (topics.PLANNER_STATUS, topics.PERCEPTION_STATUS)
        )
        pubs = {
            key: probe.publisher(topic.msg_type, topic.name, topic.qos())
            for key, topic in (
                ("color", topics.COLOR),
                ("depth", topics.DEPTH),
                ("info", topics.CAMERA_INFO),
                ("pose", topics.POSE),
            )
        }
        client = probe.node.create_client(
            topics.NEXT_BEST_VIEW.srv_type, topics.NEXT_BEST_VIEW.name
        )
        manager = None
        launcher.start()
        try:
            if not launcher.wait_for(lambda: client.wait_for_service(timeout_sec=0.1), 120):
                raise RuntimeError("planner service did not come up:\n" + "\n".join(lines[-20:]))
            if not launcher.wait_for(
                lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()), 60
            ):
                raise RuntimeError("nodes did not subscribe:\n" + "\n".join(lines[-20:]))
            pids = {name: proc.pid for name, proc in launcher.processes.items()}
            run.rss_idle = {name: rss_mb(pid) for name, pid in pids.items()}
            run.rss_peak = dict(run.rss_idle)
            manager = _start_manager(plan_every_s, launcher.env)
            reader = _read_manager(manager, run)
            statuses = (planner_status, perception_status)
            _stream(run, pubs, views, count, rate_hz, launcher, pids, statuses)
            # the manager asks once the planner has fused a frame: on a busy machine that can
            # come after a short stream, so it keeps asking until it has had an answer
            launcher.wait_for(lambda: run.latencies or run.empty_plans, FIRST_ANSWER_WAIT_S)
            _stop_manager(manager)
            reader.join(timeout=120)
            # caught up: every frame sent is accounted for by perception (published, or
            # dropped and counted) and every one it published by the planner (fused, or
            # dropped and counted); a frame neither node counts is lost on the way
            run.caught_up = launcher.wait_for(
                lambda: (
                    perception_accounted(_last(perception_status)) == len(run.sent)
                    and planner_accounted(_last(planner_status))
                    == _last(perception_status).get("frames_published")
                ),
                180,
            )
            run.drain_s = time.perf_counter() - run.stream_t0 - run.stream_s
            run.rss_end = {name: rss_mb(pid) for name, pid in pids.items()}
        finally:
            if manager is not None:
                _stop_manager(manager)
            launcher.stop()
    figures = _figures(run, scene.name, width, height, rate_hz, mask_lag_s, rebuild_nice)
    figures |= _status_figures(run, planner_status, perception_status, lines)
    if print_table:
        _print_table(figures)
    if json_out is not None:
        Path(json_out).write_text(json.dumps(figures, indent=1))
    return figures


def _last(statuses: list) -> dict:
    return json.loads(statuses[-1].data) if statuses else {}


def _read_manager(manager: subprocess.Popen, run: _Run) -> threading.Thread:
    """Read the mission manager's lines (one per request, see soak_manager) into `run` on a
    thread, once it says it is ready."""
    ready = threading.Event()

    def read() -> None:
        for line in manager.stdout:
            record = json.loads(line)
            if record.get("ready"):
                ready.set()
            elif "error" in record:
                run.empty_plans.append(record["error"])
            else:
                run.latencies.append(record["round_trip_s"])
                run.breakdown.append(record["split_s"])
                if record["views"] != 1:
                    run.empty_plans.append(f"empty plan (stamp {record['stamp_ns']})")

    reader = threading.Thread(target=read, name="soak-manager-lines", daemon=True)
    reader.start()
    if not ready.wait(120):
        raise RuntimeError("the mission manager process did not find the planner service")
    return reader


def _stream(
    run: _Run,
    pubs: dict,
    views: list,
    count: int,
    rate_hz: float,
    launcher: Any,
    pids: dict[str, int],
    statuses: tuple[list, list],
) -> None:
    """Publish `count` frames at `rate_hz` with fresh stamps; sample the nodes' memory."""
    from area3d_msgs_py import codecs, msgs

    t0 = time.perf_counter()
    for k in range(count):
        due = t0 + k / rate_hz
        now = time.perf_counter()
        if now < due:
            time.sleep(due - now)
        elif now - due > 1.0 / rate_hz:
            run.late += 1  # this process could not keep the rate: said, not hidden
        rgb, depth, K, T = views[k % len(views)]
        stamp = time.time_ns()
        frame_id = "camera_optical_frame"
        height, width = depth.shape
        pubs["info"].publish(codecs.intrinsics_to_camera_info(K, width, height, stamp, frame_id))
        pubs["pose"].publish(
            msgs.PoseStamped(header=codecs.header(stamp, "world"), pose=codecs.matrix_to_pose(T))
        )
        pubs["color"].publish(codecs.image_to_msg(rgb, "rgb8", stamp, frame_id))
        pubs["depth"].publish(codecs.image_to_msg(depth, "32FC1", stamp, frame_id))
        run.sent.append(stamp)
        if k % int(rate_hz) == 0:  # once a second
            launcher.check()
            for name, pid in pids.items():
                run.rss_peak[name] = max(run.rss_peak[name], rss_mb(pid))
        if k == count // 10:
            run.rss_start = {name: rss_mb(pid) for name, pid in pids.items()}
            run.warm = (len(statuses[0]), len(statuses[1]), len(run.latencies))
        if (k + 1) % max(1, count // 10) == 0:  # the curve: flat, or growing to a bound
            for name, pid in pids.items():
                run.rss_tenths.setdefault(name, []).append(round(rss_mb(pid)))
                for part, mb in rss_parts_mb(pid).items():
                    run.rss_parts_tenths.setdefault(name, {}).setdefault(part, []).append(round(mb))
    run.stream_t0, run.stream_s = t0, time.perf_counter() - t0


def _figures(
    run: _Run,
    scene: str,
    width: int,
    height: int,
    rate_hz: float,
    mask_lag_s: float,
    rebuild_nice: int,
) -> dict:
    """The stream's own figures: frames, timing, memory, request round trips."""
    lat = np.asarray(run.latencies) if run.latencies else np.full(1, np.nan)
    # after the first tenth of the stream (warm: numba kernels loaded, the middleware's pools grown)
    lat_warm = lat[run.warm[2] :] if lat[run.warm[2] :].size else np.full(1, np.nan)
    return {
        "scene": scene,
        "image": f"{width}x{height}",
        "rate_hz": rate_hz,
        "mask_lag_s": mask_lag_s,
        "rebuild_nice": rebuild_nice,
        "frames_sent": len(run.sent),
        "caught_up": run.caught_up,
        "stream_s": run.stream_s,
        "drain_after_stream_s": run.drain_s,
        "late_publishes": run.late,
        "rss_idle_mb": run.rss_idle,
        "rss_start_mb": run.rss_start,
        "rss_end_mb": run.rss_end,
        "rss_peak_mb": run.rss_peak,
        "rss_tenths_mb": run.rss_tenths,
        "rss_parts_tenths_mb": run.rss_parts_tenths,
        "plan_requests": len(run.latencies),
        "plan_failures": run.empty_plans,
        "plan_p50_s": float(np.percentile(lat, 50)),
        "plan_p95_s": float(np.percentile(lat, 95)),
        "plan_max_s": float(lat.max()),
        "plan_warm_p50_s": float(np.percentile(lat_warm, 50)),
        "plan_warm_p95_s": float(np.percentile(lat_warm, 95)),
        # the planner's own account, p50 and p95: waiting for the frame, for the masks, selecting;
        # the rest of a round trip is transport and the executors' queues
        "plan_parts_p50_s": _parts(run.breakdown, 50),
        "plan_parts_p95_s": _parts(run.breakdown, 95),
        "target_plan_p95_s": TARGET_PLAN_P95_S,
        # every request's round trip and the planner's split of it, in order
        "plan_round_trips_s": [round(v, 4) for v in run.latencies],
        "plan_splits_s": run.breakdown,
    }


def _status_figures(
    run: _Run, planner_status: list, perception_status: list, lines: list[str]
) -> dict:
    """The nodes' own account, from their status lines after the first tenth of the stream."""
    ages = {
        "perception": _ages(perception_status[run.warm[1] :], "last_frame_age_s"),
        "planner_paired": _ages(planner_status[run.warm[0] :], "last_paired_age_s"),
        "planner": _ages(planner_status[run.warm[0] :], "last_fused_age_s"),
    }
    fusion_s = _ages(planner_status[run.warm[0] :], "last_fusion_s")
    return {
        "frames_published_by_perception": _last(perception_status).get("frames_published"),
        "frames_fused": _last(planner_status).get("frames_fused"),
        # age of each frame when perception published it / when the planner had all its parts /
        # when the planner had fused it (their statuses, after the first tenth): p50, p95, max
        # (the planner's figures are sampled at each status it sends: most frames, not all)
        "frame_age_s": {name: _p50_p95_max(a) for name, a in ages.items()},
        # one frame's fusion in the planner, p50 / p95 / max
        "fusion_s": _p50_p95_max(fusion_s),
        "perception_rejected": _last(perception_status).get("rejected"),
        "perception_frames_dropped": {
            k: dropped(_last(perception_status), (k,)) for k in PERCEPTION_DROPS
        },
        "planner_frames_dropped_no_pose": dropped(
            _last(planner_status), ("frames_dropped_no_pose",)
        ),
        "planner_parts_dropped": _last(planner_status).get("parts_dropped_unpaired"),
        "planner_frames_dropped_backlog": _last(planner_status).get("frames_dropped_backlog"),
        "drop_lines": [line for line in lines if " dropped: " in line][:5],
        "planner_fused_ages_s": [round(float(v), 4) for v in ages["planner"]],
    }


def _start_manager(period_s: float, env: dict) -> subprocess.Popen:
    """The mission manager (`soak_manager`), a process of its own: its requests and the camera's
    publishing do not share an interpreter, as on a robot."""
    return subprocess.Popen(
        [sys.executable, "-m", "area3d_bench.soak_manager", "--period", str(period_s)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )


def _stop_manager(manager: subprocess.Popen) -> None:
    """Close its stdin (it stops after the request in flight) and wait; kill it if it hangs."""
    if manager.stdin and not manager.stdin.closed:
        manager.stdin.close()
    try:
        manager.wait(timeout=120)
    except subprocess.TimeoutExpired:
        manager.kill()
        manager.wait()


def _ages(statuses: list, key: str) -> np.ndarray:
    """The `key` values (seconds) in a node's status messages that carry one ([NaN] if none do)."""
    values = [json.loads(m.data).get(key) for m in statuses]
    values = [v for v in values if v is not None]
    return np.asarray(values, float) if values else np.full(1, np.nan)


def _p50_p95_max(values: np.ndarray) -> list[float]:
    return [float(np.percentile(values, 50)), float(np.percentile(values, 95)), float(values.max())]


def _parts(breakdown: list[dict], q: float) -> dict:
    """{part: q-th percentile, seconds} of the planner's per-request split (`last_request_s`)."""
    return {
        key: float(np.percentile([b[key] for b in breakdown if key in b], q))
        for key in ("wait_fused", "wait_cache", "select", "masks_behind")
        if any(key in b for b in breakdown)
    }


def _print_table(f: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(
        title=f"soak: {f['frames_sent']} frames {f['image']} at {f['rate_hz']:g} Hz, {f['scene']}, "
        f"planner mask_lag_s={f['mask_lag_s']:g} rebuild_nice={f['rebuild_nice']}"
    )
    for column in ("figure", "value", "target"):
        table.add_column(column, justify="left" if column == "figure" else "right")
    table.add_row("frames sent by the camera", str(f["frames_sent"]), "")
    table.add_row(
        "published by perception", str(f["frames_published_by_perception"]), "= frames sent"
    )
    for name, count in f["perception_frames_dropped"].items():
        table.add_row(f"perception: {name.replace('_', ' ')}", str(count), "0")
    table.add_row("fused by the planner", str(f["frames_fused"]), "= frames sent")
    table.add_row("planner: parts dropped unpaired", str(f["planner_parts_dropped"]), "0")
    table.add_row(
        "planner: frames dropped, fusion backlog full",
        str(f["planner_frames_dropped_backlog"]),
        "0",
    )
    table.add_row(
        "stream / drain after it", f"{f['stream_s']:.0f} s / {f['drain_after_stream_s']:.1f} s", ""
    )
    table.add_row("camera publishes late (> 1 period)", str(f["late_publishes"]), "0")
    for name in f["rss_start_mb"]:
        idle, start = f["rss_idle_mb"][name], f["rss_start_mb"][name]
        end, peak = f["rss_end_mb"][name], f["rss_peak_mb"][name]
        table.add_row(
            f"{name} RSS idle / after 1/10 of the stream -> end (peak)",
            f"{idle:.0f} / {start:.0f} -> {end:.0f} ({peak:.0f}) MB",
            "start = end",
        )
    for name, tenths in f["rss_tenths_mb"].items():
        table.add_row(
            f"{name} RSS at each tenth of the stream", " ".join(map(str, tenths)) + " MB", ""
        )
        for part, values in f["rss_parts_tenths_mb"].get(name, {}).items():
            table.add_row(f"  of which {part}", " ".join(map(str, values)) + " MB", "")
    table.add_row(
        f"next view during fusion ({f['plan_requests']} requests) p50 / p95 / max",
        f"{f['plan_p50_s'] * 1e3:.0f} / {f['plan_p95_s'] * 1e3:.0f} / {f['plan_max_s'] * 1e3:.0f} ms",
        f"p95 < {f['target_plan_p95_s'] * 1e3:.0f} ms",
    )
    behind = [f[f"plan_parts_p{q}_s"].get("masks_behind") for q in (50, 95)]
    if None not in behind:
        table.add_row(
            "  masks planned with, behind the request's frame, p50 / p95",
            f"{behind[0]:.2f} / {behind[1]:.2f} s",
            f"<= mask_lag_s {f['mask_lag_s']:g} s without waiting",
        )
    for q in (50, 95):
        parts = f[f"plan_parts_p{q}_s"]
        if parts:
            table.add_row(
                f"  planner's split, p{q}: wait for the frame / for the masks / select",
                " / ".join(
                    f"{parts.get(k, float('nan')) * 1e3:.0f}"
                    for k in ("wait_fused", "wait_cache", "select")
                )
                + " ms",
                "",
            )
    table.add_row(
        "  after the first tenth of the stream, p50 / p95",
        f"{f['plan_warm_p50_s'] * 1e3:.0f} / {f['plan_warm_p95_s'] * 1e3:.0f} ms",
        f"p95 < {f['target_plan_p95_s'] * 1e3:.0f} ms",
    )
    for name, (p50, p95, top) in f["frame_age_s"].items():
        what = {
            "perception": "published by perception",
            "planner_paired": "whole at the planner",
            "planner": "fused by the planner",
        }[name]
        table.add_row(
            f"frame age once {what}, p50 / p95 / max",
            f"{p50 * 1e3:.0f} / {p95 * 1e3:.0f} / {top * 1e3:.0f} ms",
            "",
        )
    p50, p95, top = f["fusion_s"]
    table.add_row(
        "one frame's fusion in the planner, p50 / p95 / max",
        f"{p50 * 1e3:.0f} / {p95 * 1e3:.0f} / {top * 1e3:.0f} ms",
        "",
    )
    table.add_row("requests without a plan", str(len(f["plan_failures"])), "0")
    Console().print(table)
    for line in f["drop_lines"]:
        print(line)


if __name__ == "__main__":
    run_bench()
