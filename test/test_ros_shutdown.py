"""deepprompt_ros.ros.shutdown.spin_until_shutdown: a node process's spin ends cleanly when the process is
asked to stop, also when the executor sees the context shut down while it builds its wait set (RCLError),
also when the SIGINT's KeyboardInterrupt surfaces as the cause of another error (raised inside a
pybind11 call), and any other error still propagates. A real rclpy context; no DDS traffic."""
import pytest
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

from deepprompt_ros.ros.shutdown import spin_until_shutdown


@pytest.fixture()
def context():
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def test_a_shut_down_context_ends_the_spin_whatever_the_executor_raises(context):
    node = rclpy.create_node("spin_test", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    rclpy.shutdown(context=context)  # as the signal handler does
    with pytest.raises(RuntimeError, match="context is not valid"):  # the executor's RCLError, not a clean stop
        executor.spin_once(timeout_sec=0.1)
    spin_until_shutdown(lambda: executor.spin_once(timeout_sec=0.1), context)  # returns

    def stopped():
        raise ExternalShutdownException()
    spin_until_shutdown(stopped, context)
    node.destroy_node()


def test_an_error_while_the_context_runs_or_another_error_propagates(context):
    def fail():
        raise _rclpy.RCLError("failed to initialize wait set")
    with pytest.raises(RuntimeError, match="wait set"):
        spin_until_shutdown(fail, context)
    rclpy.shutdown(context=context)

    def other():
        raise ValueError("a bug")
    with pytest.raises(ValueError, match="a bug"):
        spin_until_shutdown(other, context)


def test_an_error_caused_by_a_keyboard_interrupt_is_a_stop_and_one_caused_by_a_bug_is_not(context):
    def deserialize(cause):  # as pybind11 reports a KeyboardInterrupt raised inside the message's __init__
        try:
            raise cause
        except BaseException as inner:
            raise TypeError("Unable to convert function return value to a Python type!") from inner

    spin_until_shutdown(lambda: deserialize(KeyboardInterrupt()), context)  # returns, context still running

    def handled():  # raised while handling the interrupt (implicit chaining)
        try:
            raise KeyboardInterrupt()
        except KeyboardInterrupt:
            raise ValueError("while the interrupt is handled")
    spin_until_shutdown(handled, context)
    with pytest.raises(TypeError, match="Unable to convert"):
        spin_until_shutdown(lambda: deserialize(ValueError("bad message")), context)
