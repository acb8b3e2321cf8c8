"""Every test process talks ROS 2 on its own domain with discovery kept on this machine."""

from __future__ import annotations

import os

from area3d_msgs_py import middleware

# A domain held for the whole session, as `area3d run` holds one (a lock file, its discovery
# port free): no other pytest session or episode on this machine can be given it. Picked in
# 1..101, whose ports lie below the kernel's ephemeral range, where a socket opened by any
# process could take a participant's port first.
os.environ.pop("ROS_DOMAIN_ID", None)
_DOMAIN = middleware.DomainLease()
os.environ["ROS_DOMAIN_ID"] = str(_DOMAIN.domain_id)
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

middleware.configure()


def pytest_sessionstart(session) -> None:
    """Compile the numba kernels into their on-disk cache once, before any test waits on a node
    process that would otherwise compile them inside a bounded wait: on a fresh checkout of a busy
    2-core machine the first compile takes tens of seconds. A tiny in-process episode with camera
    and with stereo depth, and the evaluation of one, run every kernel family the nodes use;
    with the cache warm this takes a few seconds."""
    import tempfile
    import time
    from pathlib import Path

    from area3d_bringup.inprocess import run_inprocess_episode
    from area3d_eval.evaluate import evaluate_run

    small = {"width": 160, "height": 120}
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="area3d-kernels-") as out:
        for name, overrides in (
            ("camera", {"sim_bridge": small, "planner": small}),
            (
                "stereo",
                {
                    "sim_bridge": {**small, "stereo": True},
                    "perception": {"backend": "stereo"},
                    "planner": small,
                },
            ),
        ):
            run = run_inprocess_episode(
                "single_object", "area3d", 0, Path(out), budget=6, overrides=overrides,
                run_name=name, depth_source="estimated",
            )  # fmt: skip
        evaluate_run(run, checkpoints=[6], eval_width=64, eval_height=48, write=False)
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None:
        reporter.write_line(f"numba kernels compiled or loaded in {time.monotonic() - t0:.1f} s")
