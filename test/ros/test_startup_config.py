"""An invalid read-only parameter stops the installed joiner at start-up: exit code 2, a message naming it."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize(
    ("params", "expected"),
    [
        ({"mode": "online_dc"}, "parameter mode='online_dc' is not valid: allowed values are ['sequential', 'dc', 'online-dc']"),
        ({"mode": "dc"},
         "parameter mode='dc' is not allowed with map_type='as-is': allowed values are ['sequential', 'online-dc']"),
        ({"map_type": "features"}, "parameter map_type='features' is not valid: allowed values are ['as-is', 'feature-only']"),
    ],
)
def test_invalid_read_only_parameter_exits_with_code_2(start_joiner, params, expected):
    joiner = start_joiner(**params)
    code = joiner.process.wait(timeout=60)
    _, output = joiner.stop()
    assert code == 2, output
    assert expected in output, output
