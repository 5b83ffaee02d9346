"""docs/parameters.md is what tools/gen_parameters_doc.py renders from the parameter declarations now."""
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import gen_parameters_doc  # noqa: E402

from deepprompt_ros.common.params import specs_of  # noqa: E402


def test_parameters_doc_is_current():
    text = gen_parameters_doc.render()
    current = gen_parameters_doc.OUTPUT.read_text() if gen_parameters_doc.OUTPUT.is_file() else ""
    assert current == text, (f"docs/parameters.md is out of date with the parameter declarations; regenerate it: "
                             f"{gen_parameters_doc.COMMAND}")


def test_parameters_doc_covers_every_node_and_launch():
    text = gen_parameters_doc.render()
    for node, target, config in gen_parameters_doc.NODES:
        assert f"### {node}\n" in text and (ROOT / "config" / config).is_file()
        for spec in specs_of(gen_parameters_doc._load(target)):
            assert f"| `{spec.name}` |" in text
    for name in ("demo", "primitive_server", "record"):
        assert f"### {name}.launch.py\n" in text
    assert "| `objects.cube" not in text and "| `mass` |" in text  # object fields by their own names
    assert "## Training configuration\n" in text


def test_exclusive_lower_bound_is_checked_and_shown_open():
    import dataclasses

    import pytest

    from deepprompt_ros.common.params import check, markdown_table, param

    @dataclasses.dataclass(frozen=True)
    class Bounds:
        rate: float = param(1.0, "a rate", gt=0.0)
        share: float = param(0.5, "a share", gt=0.0, max=1.0)

    rate, share = specs_of(Bounds)
    assert check(rate, 0.0) == "rate = 0.0: expected a value in (0, inf)" and check(rate, 1e-12) == ""
    assert check(share, 1.0) == "" and check(share, 1.5) == "share = 1.5: expected a value in (0, 1]"
    table = markdown_table(specs_of(Bounds))
    assert "| `rate` | double | `1.0` | (0, inf) |" in table and "| `share` | double | `0.5` | (0, 1] |" in table
    with pytest.raises(TypeError, match="min .* or gt"):
        param(1.0, "both bounds", min=0.0, gt=0.0)
