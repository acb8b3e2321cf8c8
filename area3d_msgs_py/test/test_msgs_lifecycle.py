import threading

from area3d_msgs_py.lifecycle import PublishGate


def test_a_closed_gate_refuses_later_publishes_and_waits_for_one_in_progress():
    gate = PublishGate()
    inside = threading.Event()
    release = threading.Event()
    published = []

    def worker():
        with gate as running:
            inside.set()
            release.wait(30)
            if running:
                published.append("during")

    t = threading.Thread(target=worker)
    t.start()
    assert inside.wait(30)
    closer = threading.Thread(target=gate.close)
    closer.start()
    closer.join(0.2)
    assert closer.is_alive()  # close waits for the publish in progress
    release.set()
    t.join(30)
    closer.join(30)
    assert not closer.is_alive()
    assert published == ["during"]
    with gate as running:
        assert not running  # every publish after close is refused
