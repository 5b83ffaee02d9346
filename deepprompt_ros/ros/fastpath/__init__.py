"""Everything the nodes do around rclpy's public API, each piece in a module of its own with a test
of its own (``test/test_ros_fastpath_<module>.py``):

* :mod:`.wire` -- serialized message templates and the joint-command reader (hand-written CDR),
  checked byte for byte against ``rclpy.serialization``;
* :mod:`.polled` -- subscriptions and services that no executor waits on, and taking their
  messages directly (rclpy's private subscription handle);
* :mod:`.service_thread` -- services answered by a thread of their own on an rcl wait set (rclpy's
  private ``implementation_singleton``);
* :mod:`.service_client` -- its client-side mirror: a service call whose caller waits for the
  response on a wait set of its own (used by the benchmark's Condition client);
* :mod:`.realtime` -- real-time scheduling, CPU affinity, the interpreter's switch interval,
  garbage-collector freezing, OS thread names.

The nodes' parameter ``fast_path: false`` (primitive_server, sim_bridge, demo_recorder) replaces
the first three by plain rclpy (executor-dispatched services and subscriptions, rclpy messages);
an rclpy release that breaks them is caught by their tests.
"""
