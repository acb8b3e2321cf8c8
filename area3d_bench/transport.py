"""`area3d bench transport`: the graph's transport between two processes, each figure beside its
target and the ratio.

- topics (`area3d_bench.topic_latency`): publish-to-receive latency and throughput of a 640x480 rgb8
  image, a 640x480 32FC1 depth image and a 1M-point PointCloud2;
- the next-best-view services (`planner_service.bench_transport`): the round trip of one closed-loop view against
  a planner node process with a warm cache at object level, over GetPlan and over NextBestView
  (area3d/planner/select_views).

Both run on rclpy with the middleware setup of the graph (`area3d_msgs_py.middleware`).
"""

from __future__ import annotations

import os


def run_bench(samples: int = 200, cloud_samples: int = 20, requests: int = 50) -> dict:
    from rich.console import Console
    from rich.table import Table

    from area3d_bench.planner_service import bench_transport
    from area3d_bench.topic_latency import measure_topics
    from area3d_msgs_py import middleware

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    with middleware.DomainLease() as lease:
        os.environ["ROS_DOMAIN_ID"] = str(lease.domain_id)
        results: dict = dict(measure_topics(samples, cloud_samples))
        try:
            results["getplan"] = bench_transport(requests)
        except Exception as exc:  # print what was measured, say why this one is missing
            results["getplan"] = {"error": f"{type(exc).__name__}: {exc}"}
    transport = os.environ.get(middleware.TRANSPORT_ENV, "shm")
    table = Table(
        title=f"transport, two processes (rclpy, rmw_fastrtps_cpp, profile {transport!r})"
    )
    for column in ("message", "received", "p50 ms", "p95 ms", "target p95", "ratio", "MB/s"):
        table.add_column(column, justify="right")
    labels = {"rgb8": "640x480 rgb8", "32FC1": "640x480 32FC1", "cloud": "1M-point cloud (16 MB)"}
    for key, label in labels.items():
        r = results[key]
        table.add_row(
            label,
            f"{r['received']}/{r['sent']}",
            f"{r['p50_ms']:.2f}",
            f"{r['p95_ms']:.2f}",
            f"< {r['target_p95_ms']:.0f} ms",
            f"{r['p95_ms'] / r['target_p95_ms']:.2f}",
            f"{r['mb_per_s']:.0f}",
        )
    r = results["getplan"]
    if "error" in r:
        table.add_row("next-best-view round trips", "skipped", r["error"], "", "", "", "")
    else:
        for label, key, target in (
            ("GetPlan round trip (1 view)", "round_trip", r["target_p95_s"]),
            ("NextBestView round trip (1 view)", "select_views", r["select_views_target_p95_s"]),
        ):
            table.add_row(
                label,
                f"{r['requests']}/{r['requests']}",
                f"{r[f'{key}_p50_s'] * 1e3:.1f}",
                f"{r[f'{key}_p95_s'] * 1e3:.1f}",
                f"< {target * 1e3:.0f} ms",
                f"{r[f'{key}_p95_s'] / target:.2f}",
                "",
            )
    Console().print(table)
    return results


if __name__ == "__main__":
    run_bench()
