"""The camera-input QoS choice: a best-effort publisher (a camera driver's sensor-data profile)
reaches a `sensor_data` reader and never a `reliable` one, which is told by an incompatible-QoS
event; a reliable publisher reaches both."""

import threading

import pytest
from rclpy.event_handler import SubscriptionEventCallbacks

from area3d_msgs_py import msgs, qos
from area3d_msgs_py.errors import InputError
from area3d_msgs_py.probe import Probe

TIMEOUT_S = 120.0  # generous: DDS discovery on a loaded machine


def test_the_camera_qos_choice_is_checked_and_names_the_field():
    assert qos.parse_camera_qos("sensor_data") == "sensor_data"
    with pytest.raises(InputError) as refused:
        qos.camera_input("best_effort", field="color_qos")
    assert refused.value.field == "color_qos" and refused.value.value == "best_effort"
    assert "reliable, sensor_data" in str(refused.value)
    profile = qos.camera_input("sensor_data")
    assert profile.reliability == qos.ReliabilityPolicy.BEST_EFFORT
    assert profile.durability == qos.DurabilityPolicy.VOLATILE
    assert profile.history == qos.HistoryPolicy.KEEP_LAST
    assert qos.camera_input("reliable").reliability == qos.ReliabilityPolicy.RELIABLE


def _readers(probe: Probe, topic: str) -> dict:
    """A reliable and a sensor_data reader of `topic`, with what each received and whether an
    incompatible-QoS event came."""
    readers = {}
    for choice in qos.CAMERA_QOS_CHOICES:
        got, incompatible = [], threading.Event()
        probe.node.create_subscription(
            msgs.String,
            topic,
            got.append,
            qos.camera_input(choice),
            event_callbacks=SubscriptionEventCallbacks(
                incompatible_qos=lambda _info, event=incompatible: event.set()
            ),
        )
        readers[choice] = (got, incompatible)
    return readers


def test_a_best_effort_driver_reaches_a_sensor_data_reader_and_not_a_reliable_one():
    with Probe("camera_driver") as driver, Probe("camera_reader") as reader:
        readers = _readers(reader, "camera/color/image_raw")
        publisher = driver.publisher(msgs.String, "camera/color/image_raw", qos.sensor_data(5))
        got, _ = readers["sensor_data"]
        # best effort may lose a sample: publish until one arrives
        assert reader.wait_for(
            lambda: publisher.publish(msgs.String(data="frame")) or got, TIMEOUT_S, poll_s=0.05
        ), "the sensor_data reader received nothing from a best-effort publisher"
        never, incompatible = readers["reliable"]
        assert incompatible.wait(TIMEOUT_S), "no incompatible-QoS event on the reliable reader"
        assert publisher.get_subscription_count() == 1  # only the sensor_data reader matched
        assert never == []


def test_a_reliable_driver_reaches_both_readers():
    with Probe("camera_driver") as driver, Probe("camera_reader") as reader:
        readers = _readers(reader, "camera/depth/image_raw")
        publisher = driver.publisher(msgs.String, "camera/depth/image_raw", qos.frames())
        assert driver.wait_for_readers(publisher, 2, TIMEOUT_S)
        # the best-effort reader drops what arrives before it has matched the writer in turn
        assert reader.wait_for(
            lambda: (
                publisher.publish(msgs.String(data="frame"))
                or all(got for got, _ in readers.values())
            ),
            TIMEOUT_S,
            poll_s=0.05,
        ), {choice: len(got) for choice, (got, _) in readers.items()}
        for got, incompatible in readers.values():
            assert got[0].data == "frame" and not incompatible.is_set()


def test_a_reader_that_a_best_effort_driver_cannot_reach_says_so_in_its_status_and_diagnostics():
    """Nothing arrives on a reliable reader beside a best-effort driver, and no callback runs:
    the event is logged once, by the topic as remapped, and kept in the status, which the
    diagnostics read as a standing warning."""
    from area3d_msgs_py.diagnostics import WARN, assess
    from area3d_msgs_py.guard import Rejections, guarded

    with Probe("camera_driver") as driver, Probe("camera_reader") as reader:
        rejections = Rejections()
        warnings = []
        topic = "camera/color/image_raw"

        class Logged:  # the reader's node, its warnings kept
            resolve_topic_name = reader.node.resolve_topic_name

            def get_logger(self):
                return self

            def warning(self, message):
                warnings.append(message)

        got = []
        reader.node.create_subscription(
            msgs.String, topic, guarded(Logged(), got.append, topic, rejections),
            qos.camera_input("reliable"), event_callbacks=rejections.qos_events(Logged(), topic),
        )  # fmt: skip
        publisher = driver.publisher(msgs.String, topic, qos.sensor_data(5))
        assert reader.wait_for(lambda: "incompatible_qos" in rejections.snapshot(), TIMEOUT_S)
        publisher.publish(msgs.String(data="frame"))
        snapshot = rejections.snapshot()
        assert snapshot["incompatible_qos"] == {"/camera/color/image_raw": "RELIABILITY"}
        assert snapshot["total"] == 0  # nothing rejected: nothing arrived
        assert len(warnings) == 1 and warnings[0].startswith("/camera/color/image_raw: a publisher")
        assert "camera_qos: sensor_data" in warnings[0]
        verdict = assess({"rejected": snapshot})
        assert verdict.level == WARN
        assert "nothing arrives on /camera/color/image_raw" in verdict.message
        assert assess({"rejected": Rejections().snapshot()}).level != WARN
        # the driver restarted reliable: its frames arrive, and the warning is gone
        fixed = driver.publisher(msgs.String, topic, qos.frames())
        assert reader.wait_for(
            lambda: fixed.publish(msgs.String(data="frame")) or got, TIMEOUT_S, poll_s=0.05
        )
        assert "incompatible_qos" not in rejections.snapshot()
