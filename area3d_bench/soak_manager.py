"""The soak's mission manager, a process of its own as on a robot: once the planner has fused a
frame (its status says so; before, the answer is an empty plan), once a period it asks the
planner for the next view from the newest camera pose it has seen (naming that pose's stamp, so
the planner plans from that frame) and prints one JSON line per request to stdout: the round
trip, and the planner's own split of it from the status that follows the answer.

    python -m area3d_bench.soak_manager --period 1.0

It stops when its stdin closes (the benchmark closes it), so it never depends on a signal
reaching a process blocked in the middleware.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time

ANSWER_WAIT_S = 60.0
STATUS_WAIT_S = 5.0  # the planner publishes its status 0.05 s after each answer


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--period", type=float, default=1.0, help="seconds between requests")
    args = parser.parse_args(argv)

    from area3d_msgs_py import codecs, middleware, msgs, topics
    from area3d_msgs_py.probe import Probe

    middleware.configure()
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    with Probe("soak_mission_manager") as probe:
        poses = probe.listen(topics.POSE.msg_type, topics.POSE.name, topics.POSE.qos())
        statuses = probe.listen(
            topics.PLANNER_STATUS.msg_type, topics.PLANNER_STATUS.name, topics.PLANNER_STATUS.qos()
        )
        service = topics.NEXT_BEST_VIEW
        client = probe.node.create_client(service.srv_type, service.name)
        while not stop.is_set() and not client.wait_for_service(timeout_sec=0.5):
            pass
        print(json.dumps({"ready": True}), flush=True)
        mapped = False  # the planner has fused a frame
        while not stop.wait(args.period):
            # frames_fused only grows: the newest status says whether any frame was fused
            mapped = mapped or bool(
                statuses and json.loads(statuses[-1].data).get("frames_fused", 0) > 0
            )
            if not poses or not mapped:
                continue
            newest = poses[-1]
            request = msgs.GetPlan_Request()
            request.start = newest
            request.goal.pose.position.x = 1.0  # one view
            # the status that follows the answer carries its split; it may arrive before the
            # answer does, so the statuses are counted before the request goes out
            seen = len(statuses)
            answered_before = (
                json.loads(statuses[-1].data).get("requests_answered", 0) if statuses else 0
            )
            answered = threading.Event()
            t = time.perf_counter()
            future = client.call_async(request)
            future.add_done_callback(lambda _, done=answered: done.set())
            if not answered.wait(ANSWER_WAIT_S):
                print(json.dumps({"error": f"no answer within {ANSWER_WAIT_S} s"}), flush=True)
                continue
            round_trip = time.perf_counter() - t
            split = {}
            deadline = time.monotonic() + STATUS_WAIT_S
            while time.monotonic() < deadline and not split:
                for status in list(statuses[seen:]):
                    line = json.loads(status.data)
                    if line.get("requests_answered", 0) > answered_before:
                        split = line.get("last_request_s", {})
                        break
                time.sleep(0.01)
            record = {
                "stamp_ns": codecs.stamp_to_ns(newest.header.stamp),
                "round_trip_s": round(round_trip, 4),
                "views": len(future.result().plan.poses),
                "split_s": split,
            }
            print(json.dumps(record), flush=True)
            del poses[:-1], statuses[:-1]  # keep only the newest of each
    return 0


if __name__ == "__main__":
    sys.exit(main())
