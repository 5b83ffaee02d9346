"""ros.parameters: node parameters declared from a configuration dataclass (common.params), on
in-process rclpy nodes: values and overrides, the descriptors ``ros2 param describe`` shows, every
invalid value reported at once, per-object prefixes; the configuration dataclasses of sim_bridge
and demo_recorder."""
from __future__ import annotations

import dataclasses

import pytest
import rclpy
from rcl_interfaces.msg import ParameterType
from rclpy.parameter import Parameter

from deepprompt_ros.common.params import ConfigError, param, specs_of, validate
from deepprompt_ros.recording.config import RecorderConfig
from deepprompt_ros.ros.parameters import declare_config, declare_values, descriptor
from deepprompt_ros.sim.bridge_config import ObjectConfig, SimBridgeConfig


@dataclasses.dataclass(frozen=True)
class Example:
    rate_hz: float = param(5.0, "images per second", min=0.1, max=60.0, unit="Hz", name="camera.rate_hz")
    count: int = param(3, "how many", min=1, max=10)
    mode: str = param("a", "the mode", choices=("a", "b"))
    gains: tuple[float, ...] = param((), "gains, empty = none", min=0.0, max=2.0)
    names: tuple[str, ...] = param(("x", "y"), "names")
    on: bool = param(True, "switch")

    def __post_init__(self):
        validate(self)
        if self.count > 5 and self.mode == "b":
            raise ConfigError("count = 6 with mode 'b': expected at most 5")


@pytest.fixture(scope="module")
def context():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, args=[])
    yield ctx
    rclpy.shutdown(context=ctx)


def _node(context, name, **overrides):
    params = [Parameter(k, value=v) for k, v in overrides.items()]
    return rclpy.create_node(name, context=context, parameter_overrides=params,
                             start_parameter_services=False, enable_rosout=False)


def test_defaults_and_overrides(context):
    node = _node(context, "defaults")
    try:
        assert declare_config(node, Example) == Example()
        assert node.get_parameter("camera.rate_hz").value == 5.0
        assert node.get_parameter("gains").type_ == Parameter.Type.NOT_SET  # empty list: no ROS type
    finally:
        node.destroy_node()
    node = _node(context, "overrides", **{"camera.rate_hz": 10, "count": 4, "mode": "b", "gains": [0.5, 2.0],
                                          "names": ["q"], "on": False})
    try:
        cfg = declare_config(node, Example)
        assert cfg == Example(rate_hz=10.0, count=4, mode="b", gains=(0.5, 2.0), names=("q",), on=False)
        assert isinstance(cfg.rate_hz, float) and isinstance(cfg.gains, tuple)
    finally:
        node.destroy_node()


def test_descriptors_are_read_only_with_ranges_choices_and_units(context):
    specs = {s.name: s for s in specs_of(Example)}
    d = descriptor(specs["camera.rate_hz"])
    assert d.read_only and d.dynamic_typing and d.description == "images per second"
    assert (d.floating_point_range[0].from_value, d.floating_point_range[0].to_value) == (0.1, 60.0)
    assert d.additional_constraints == "unit: Hz"
    d = descriptor(specs["count"])
    assert (d.integer_range[0].from_value, d.integer_range[0].to_value, d.integer_range[0].step) == (1, 10, 1)
    assert descriptor(specs["mode"]).additional_constraints == "one of: a, b"
    assert descriptor(specs["gains"]).additional_constraints == "each element in [0, 2]"
    node = _node(context, "describe")
    try:
        declare_config(node, Example)
        described = node.describe_parameter("count")
        assert described.read_only and described.description == "how many"
        assert described.type == ParameterType.PARAMETER_INTEGER
        result, = node.set_parameters([Parameter("count", value=2)])
        assert not result.successful and node.get_parameter("count").value == 3  # read-only
    finally:
        node.destroy_node()


def test_every_invalid_value_is_reported_at_once(context):
    node = _node(context, "invalid", **{"camera.rate_hz": 100.0, "count": "many", "mode": "c",
                                        "gains": [0.5, 3.0], "names": [1, 2], "on": 1})
    try:
        with pytest.raises(ConfigError) as info:
            declare_config(node, Example)
    finally:
        node.destroy_node()
    text = str(info.value)
    assert text.startswith("invalid parameters:\n  ")
    for line in ["camera.rate_hz = 100.0 Hz: expected a value in [0.1, 60] Hz", "count = 'many': expected an integer",
                 "mode = 'c': expected one of 'a', 'b'", "gains = [0.5, 3.0]: expected a value in [0, 2]",
                 "names = [1, 2]: expected a list of strings", "on = 1: expected true or false"]:
        assert f"\n  {line}" in text, text


def test_checks_of_several_parameters_join_the_others(context):
    node = _node(context, "cross", count=6, mode="b", on="yes")
    try:
        with pytest.raises(ConfigError) as info:
            declare_config(node, Example)
    finally:
        node.destroy_node()
    assert str(info.value) == ("invalid parameters:\n  on = 'yes': expected true or false\n"
                               "  count = 6 with mode 'b': expected at most 5")


def test_prefixed_parameters_are_named_in_full(context):
    node = _node(context, "prefixed", **{"objects.cube.mass": -1.0, "objects.cube.shape": "sphere"})
    try:
        values, errors = declare_values(node, specs_of(ObjectConfig), prefix="objects.cube.")
        assert values["shape"] == "sphere" and "mass" not in values
        assert errors == ["objects.cube.mass = -1.0 kg: expected a value in [0, 1000] kg"]
        assert node.get_parameter("objects.cube.size").value == [0.05, 0.05, 0.05]
    finally:
        node.destroy_node()


def test_node_configurations():
    assert [s.name for s in specs_of(SimBridgeConfig)][:2] == ["robot", "rate_hz"]
    assert {"camera.width", "camera.eye", "object_names"} <= {s.name for s in specs_of(SimBridgeConfig)}
    with pytest.raises(ConfigError, match=r"rate_hz = 5\.0 Hz: expected 0 \(the robot's control rate\) or a "
                                          r"value in \[10, 5000\] Hz"):
        SimBridgeConfig(rate_hz=5.0)
    assert SimBridgeConfig(rate_hz=10.0).rate_hz == 10.0
    assert RecorderConfig(context_topics=("object=objects/cube/pose", "camera/image_raw")).context_specs() == [
        ("object", "objects/cube/pose"), ("camera_image_raw", "camera/image_raw")]
    with pytest.raises(ConfigError, match="context_topics: context name '9'"):
        RecorderConfig(context_topics=("9=bad",))
    with pytest.raises(ConfigError, match="bag_compression = 'gzip': expected one of 'zstd', 'lz4', 'none'"):
        RecorderConfig(bag_compression="gzip")
