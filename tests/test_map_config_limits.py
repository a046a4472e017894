"""``[envmap]`` grid settings out of range are refused naming the file and the key.

Before: a negative ``resolution`` reached ``OccupancyGrid`` and failed there with
``resolution must be positive, got -0.1``, naming neither (docs/failures.md, "A new
user's first day").
"""

from __future__ import annotations

from pathlib import Path

import pytest

from lampsam.config_loader import ConfigError, FieldValueError, load_config
from lampsam.localization.map_config import DepthGridConfig, EnvMapConfig, LaserGridConfig


@pytest.mark.parametrize("table,key,value", [
    ("laser", "resolution", "-0.1"), ("depth", "resolution", "0"), ("laser", "min_scans", "0"),
    ("laser", "min_consistency", "1.5"), ("depth", "depth_stride", "0"),
])
def test_bad_grid_setting_names_file_and_key(tmp_path: Path, table: str, key: str,
                                             value: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(f"[envmap.{table}]\n{key} = {value}\n")
    with pytest.raises(ConfigError, match=rf"bad\.toml.*envmap\.{table}\.{key}: must be"):
        load_config(EnvMapConfig, path, table="envmap")


def test_defaults_pass_and_python_construction_is_checked() -> None:
    assert LaserGridConfig().resolution == 0.1 and DepthGridConfig().resolution == 0.05
    with pytest.raises(FieldValueError):
        LaserGridConfig(resolution=-1.0)
