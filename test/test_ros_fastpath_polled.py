"""ros/fastpath/polled.py: a subscription in a NotExecuted callback group stays on its node but no
executor runs its callback; its owner takes the messages itself (all of them in order, or only the
newest). One in-process node on an isolated network (LOCALHOST discovery, random domain)."""
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Int32

from deepprompt_ros.ros.fastpath import polled
from deepprompt_ros.ros.testing import RosTestClient, isolated_ros_env


@pytest.fixture
def client(tmp_path):
    with RosTestClient(isolated_ros_env(tmp_path / "log"), "polled_test") as c:
        yield c


def _subscribe(client, called, raw=False):
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    return client.node.create_subscription(Int32, "numbers", lambda m: called.append(m), qos,
                                           callback_group=polled.NotExecuted(), raw=raw)


def _publish(client, values):
    assert client.wait_for_subscriber("numbers", 10.0)
    for v in values:
        client.publish("numbers", Int32(data=v), qos=50)


def test_no_executor_runs_the_callback_and_take_all_yields_every_message_in_order(client):
    called = []
    sub = _subscribe(client, called)
    _publish(client, range(5))
    got = []
    assert client.wait_for(lambda: got.extend(m.data for m, _ in polled.take_all(sub)) or len(got) >= 5, 10.0)
    assert got == [0, 1, 2, 3, 4]
    client.spin_for(0.3)  # the executor spins the node: the callback still never runs
    assert called == []
    assert list(polled.take_all(sub)) == []
    # the subscription is the node's own (what `ros2 node info` lists)
    topics = dict(client.node.get_subscriber_names_and_types_by_node("polled_test", "/"))
    assert topics.get("/numbers") == ["std_msgs/msg/Int32"]


def test_take_newest_drops_the_older_messages_and_raw_gives_bytes(client):
    from rclpy.serialization import deserialize_message

    called = []
    sub = _subscribe(client, called, raw=True)
    _publish(client, [7, 8, 9])
    client.spin_for(0.5)  # all three have arrived (and no callback ran)
    newest = polled.take_newest(sub)
    assert isinstance(newest, bytes) and deserialize_message(newest, Int32).data == 9
    assert polled.take_newest(sub) is None and called == []
    _publish(client, [10])
    assert client.wait_for(lambda: (m := polled.take_newest(sub, raw=False)) is not None and m.data == 10, 10.0)


def test_the_group_refuses_execution():
    group = polled.NotExecuted()
    assert not group.can_execute(object()) and not group.beginning_execution(object())
    group.ending_execution(object())
