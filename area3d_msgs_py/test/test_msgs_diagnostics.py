"""A node's status as diagnostics: every fact a key/value, the level by the stated rules, and a
real node publishing it on /diagnostics (OK, WARN after a rejected input, OK again)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from area3d_msgs_py import codecs, msgs
from area3d_msgs_py.diagnostics import (
    DIAGNOSTICS_TOPIC,
    ERROR,
    OK,
    WARN,
    DiagnosticArray,
    assess,
    diagnostic_status,
    status_name,
)
from area3d_msgs_py.probe import Probe

REPO_ROOT = Path(__file__).resolve().parents[2]
TIMEOUT_S = 120.0

STATUS = {
    "node": "perception",
    "frames_published": 12,
    "last_frame_age_s": 0.25,
    "frames_waiting_for_camera_info": 0,
    "parts_dropped_unpaired": 2,
    "backend": "rgbd",
    "last_request_s": None,
    "rejected": {"total": 3, "by_topic": {"area3d/camera/pose": 3}, "by_field": {"orientation": 3}},
}


def _with(**changes) -> dict:
    return {**STATUS, **changes}


def test_a_status_whose_counts_did_not_rise_is_ok():
    assert assess(STATUS, STATUS).level == OK
    assert assess(STATUS, STATUS).message == "OK"


def test_frames_dropped_in_the_period_warn_naming_the_count():
    result = assess(_with(parts_dropped_unpaired=5), STATUS)
    assert result.level == WARN
    assert "3 dropped (parts_dropped_unpaired)" in result.message


def test_inputs_rejected_in_the_period_warn_naming_the_fields():
    later = _with(rejected={**STATUS["rejected"], "total": 4})
    result = assess(later, STATUS)
    assert result.level == WARN and "1 inputs rejected" in result.message
    # which fields, most first (a user read only "N inputs rejected" there)
    fields = {"orientation": 3, "encoding": 9, "header.stamp": 5, "d": 4}
    later = _with(rejected={**STATUS["rejected"], "total": 21, "by_field": fields})
    result = assess(later, STATUS)
    assert "18 inputs rejected (encoding 9, header.stamp 5, d 4)" in result.message


def test_a_standing_warning_of_the_node_warns_for_as_long_as_it_stands():
    warning = "pairing rate 0.52 below min_pairing_rate 0.8 (parts lost or stamped apart)"
    result = assess(_with(warnings=[warning]), STATUS)
    assert result.level == WARN and result.message == warning
    both = assess(_with(warnings=[warning], parts_dropped_unpaired=5), STATUS)
    assert both.level == WARN and "3 dropped" in both.message and warning in both.message
    assert assess(_with(warnings=[]), STATUS).level == OK


def test_drops_before_the_period_do_not_warn_but_the_first_status_counts_from_zero():
    assert assess(STATUS, STATUS).level == OK
    first = assess(STATUS, None)
    assert (
        first.level == WARN
        and "2 dropped" in first.message
        and "3 inputs rejected" in first.message
    )


def test_a_failed_backend_is_an_error_and_outranks_a_warning():
    result = assess(_with(backend_error="VLM server refused", parts_dropped_unpaired=9), STATUS)
    assert result.level == ERROR and "backend failed: VLM server refused" in result.message


def test_a_count_of_failures_that_rose_is_an_error():
    before = _with(analysis_failures=1)
    assert assess(_with(analysis_failures=2), before).level == ERROR
    assert assess(before, before).level == OK


def test_a_worker_that_died_is_an_error_naming_it():
    result = assess(_with(workers={"fusion": False, "rebuild": True}), STATUS)
    assert result.level == ERROR and result.message == "worker fusion died"
    assert assess(_with(workers={"fusion": True}), STATUS).level == OK


def test_every_fact_is_a_key_value_with_nested_keys_dotted():
    status = diagnostic_status("perception: status", STATUS, STATUS, hardware_id="/perception")
    values = {kv.key: kv.value for kv in status.values}
    assert values["frames_published"] == "12"
    assert values["last_frame_age_s"] == "0.25"
    assert values["last_request_s"] == ""
    assert values["rejected.total"] == "3"
    assert values["rejected.by_topic.area3d/camera/pose"] == "3"
    assert values["rejected.by_field.orientation"] == "3"
    assert values["backend"] == "rgbd"
    assert status.level == OK.to_bytes(1, "little") and status.name == "perception: status"
    assert status.hardware_id == "/perception"


def test_the_status_name_keeps_the_namespace():
    assert status_name("/planner") == "planner: status"
    assert status_name("/robot1/planner") == "robot1/planner: status"


def test_a_node_publishes_its_status_on_diagnostics_and_warns_after_a_rejected_input():
    node = subprocess.Popen(
        [sys.executable, "-m", "area3d_perception.node", "--ros-args", "-r", "__ns:=/robot1"],
        env=dict(os.environ, PYTHONPATH=str(REPO_ROOT)),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        with Probe("diagnostics_monitor") as probe:
            arrays = probe.listen(DiagnosticArray, DIAGNOSTICS_TOPIC)

            def ours(level: int | None = None) -> list:
                return [
                    s
                    for a in list(arrays)
                    for s in a.status
                    if s.name == "robot1/perception: status"
                    and (level is None or s.level == level.to_bytes(1, "little"))
                ]

            assert probe.wait_for(lambda: ours(OK), TIMEOUT_S), "no OK status on /diagnostics"
            values = {kv.key: kv.value for kv in ours(OK)[-1].values}
            assert values["frames_published"] == "0" and values["rejected.total"] == "0"

            color = probe.publisher(msgs.Image, "/robot1/area3d/camera/color/image_raw")
            assert probe.wait_for_readers(color, 1, TIMEOUT_S)
            bad = codecs.header(1_000_000_000, "camera_optical_frame")
            color.publish(msgs.Image(header=bad, encoding="rgb8", width=4, height=2, step=12))
            assert probe.wait_for(lambda: ours(WARN), TIMEOUT_S), "no WARN after a rejected input"
            warned = ours(WARN)[0]
            assert "1 inputs rejected" in warned.message
            values = {kv.key: kv.value for kv in warned.values}
            assert values["rejected.by_topic.area3d/camera/color/image_raw"] == "1"
            # and back to OK by itself once a period has passed without a rejection
            seen = len(arrays)
            assert probe.wait_for(
                lambda: any(
                    s.level == OK.to_bytes(1, "little") and s.name.startswith("robot1/perception")
                    for a in list(arrays)[seen:]
                    for s in a.status
                ),
                TIMEOUT_S,
            )
    finally:
        node.terminate()
        node.communicate(timeout=60)
