"""SyntheticTownConfig: validation names the bad setting; the route follows the frame budget."""

from __future__ import annotations

import pytest

from stablecues.errors import ConfigError
from stablecues.synthetic import SyntheticTownConfig


@pytest.mark.parametrize(
    "field,value",
    [
        ("frames", 0),
        ("width", 4),
        ("fov_deg", 200.0),
        ("baseline", 0.0),
        ("loops", -1),
        ("clutter", -1.0),
        ("route_blocks", (0, 1)),
    ],
)
def test_config_validation(field: str, value: object) -> None:
    with pytest.raises(ConfigError, match=field):
        SyntheticTownConfig(**{field: value}).validate()  # type: ignore[arg-type]


def test_route_size_follows_the_frame_budget() -> None:
    assert SyntheticTownConfig(frames=50).route_size() == (1, 1)
    big = SyntheticTownConfig(frames=3000, step=1.0).route_size()
    assert big[0] * big[1] > 1
    assert SyntheticTownConfig(route_blocks=(2, 1)).route_size() == (2, 1)
