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
    process that would otherwise compile them inside a bounded wait (`area3d_bringup.kernels`;
    `make install` has run it already, and then this loads them in a few seconds). With test
    processes (pytest-xdist), once, in the process that starts them, before it does: each would
    otherwise load every kernel (about 5 s of CPU each) whether its tests run them or not."""
    if hasattr(session.config, "workerinput"):  # a test process: the cache is written
        return
    from area3d_bringup.kernels import warm_kernels

    seconds = warm_kernels()
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None:
        reporter.write_line(f"numba kernels compiled or loaded in {seconds:.1f} s")
