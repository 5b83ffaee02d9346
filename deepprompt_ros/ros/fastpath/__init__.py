"""Everything the nodes do around rclpy's public API, each piece in a module of its own with a test
of its own: :mod:`.realtime` (real-time scheduling, CPU affinity, garbage-collector freezing, the
interpreter's switch interval, OS thread names). A node parameter (``fast_path``) selects plain
rclpy instead where a piece has a public-API equivalent."""
