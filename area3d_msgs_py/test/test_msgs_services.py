"""A service call whose reply is lost is asked again, and gives up naming the service."""

import pytest
from rclpy.task import Future

from area3d_msgs_py import services


class Client:
    """An rclpy client's calling side whose first `lost` requests get no reply."""

    service_name = "/area3d/planner/reset"

    def __init__(self, lost: int):
        self.lost, self.requests, self.removed = lost, [], []

    def call_async(self, request):
        self.requests.append(request)
        future = Future()
        if len(self.requests) > self.lost:
            future.set_result(f"reply to {request}")
        return future

    def remove_pending_request(self, future):
        self.removed.append(future)


def test_a_request_without_a_reply_is_sent_again_until_one_comes():
    client = Client(lost=2)
    assert services.call(client, "reset", timeout_s=60.0, resend_s=0.01) == "reply to reset"
    assert client.requests == ["reset"] * 3
    assert len(client.removed) == 2  # the unanswered ones are no longer waited for


def test_no_reply_at_all_is_a_timeout_naming_the_service():
    client = Client(lost=10**9)
    with pytest.raises(TimeoutError, match=r"service /area3d/planner/reset: no reply within 0.2 s"):
        services.call(client, "reset", timeout_s=0.2, resend_s=0.05)
    assert client.requests and len(client.removed) == len(client.requests)
