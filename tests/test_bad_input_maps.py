"""Bad input to the environment-map folder (``show-map``, ``localize --map``).

Before: a binary ``manifest.yaml`` or ``map.yaml`` raised
UnicodeDecodeError (exit 1, "internal error"), a ``format_version`` that is not an integer
raised ValueError from ``int()``, a NaN resolution was refused without naming the file, and
a YAML error in ``map.yaml`` came out on several lines. Each is now one error line naming
the file (exit 2).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from lampsam.cli import main
from lampsam.localization.grid import LogOddsConfig, OccupancyGrid
from lampsam.localization.map_store import load_env_map, save_layers, write_manifest


@pytest.fixture()
def env_map(tmp_path: Path) -> Path:
    """A 2 m x 1 m grid map saved as lampsam writes it (no spatial or ceiling layer)."""
    log_odds = np.zeros((20, 40))
    log_odds[0, :] = 5.0
    grid = OccupancyGrid(log_odds, 0.05, np.array([-1.0, -0.5, 0.0]))
    out = tmp_path / "MAP"
    layers = save_layers(out, grid, LogOddsConfig(), {"sensor": "test"})
    write_manifest(out, {"kind": "test"}, layers, {}, {}, {})
    return out


def test_clean_map_reads(env_map: Path) -> None:
    back = load_env_map(env_map)
    assert back.grid.resolution == pytest.approx(0.05)
    np.testing.assert_allclose(back.grid.origin, [-1.0, -0.5, 0.0], atol=1e-12)


def _binary(p: Path) -> None:
    p.write_bytes(np.random.default_rng(5).bytes(1200))


def _sub(pattern: str, repl: str):  # type: ignore[no-untyped-def]
    def edit(p: Path) -> None:
        text = p.read_text()
        new = re.sub(pattern, repl, text, count=1, flags=re.MULTILINE)
        assert new != text, (pattern, text)
        p.write_text(new)
    return edit


@pytest.mark.parametrize(("name", "corrupt", "match"), [
    ("manifest.yaml", _binary, r"manifest.yaml:\d+: not UTF-8 text"),
    ("manifest.yaml", _sub(r"^format_version: \d+", "format_version: two"),
     r"manifest.yaml: format_version must be an integer, got 'two'"),
    ("manifest.yaml", _sub(r"^format_version: \d+", "format_version: .nan"),
     r"manifest.yaml: format_version must be an integer, got nan"),
    ("map.yaml", _binary, r"map.yaml:\d+: not UTF-8 text"),
    ("map.yaml", _sub(r"^resolution: .*", "resolution: .nan"),
     r"map.yaml: resolution must be a positive number, got nan"),
    ("map.yaml", _sub(r"^resolution: .*", "resolution: [0.05"), r"map.yaml:\d+: invalid YAML"),
], ids=["manifest-binary", "manifest-version-word", "manifest-version-nan", "grid-binary",
        "grid-nan-resolution", "grid-yaml-error"])
def test_corrupt_map_is_one_error_line(env_map: Path, tmp_path: Path, name: str, corrupt,  # type: ignore[no-untyped-def]
                                       match: str, capsys: pytest.CaptureFixture[str]) -> None:
    corrupt(env_map / name)
    assert main(["show-map", str(env_map), "--out", str(tmp_path / "m.png")]) == 2
    err = capsys.readouterr().err
    assert "internal error" not in err and "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and re.search(match, lines[0]), err
    assert not (tmp_path / "m.png").exists()


@pytest.mark.parametrize("way", ["empty", "cut_short"])
def test_corrupt_distance_field_is_recomputed(env_map: Path, way: str,
                                              caplog: pytest.LogCaptureFixture) -> None:
    """A precomputed lookup that cannot be read is rebuilt with a warning (its documented
    fallback), not an EOFError / BadZipFile from inside NumPy."""
    from lampsam.localization.map_tables import (
        DISTANCE_FIELD_FILE,
        load_distance_field,
        save_distance_field,
    )

    grid = load_env_map(env_map).grid
    path = save_distance_field(env_map, grid, np.ones((grid.height, grid.width)))
    assert path.name == DISTANCE_FIELD_FILE
    assert load_distance_field(env_map, grid) is not None
    data = path.read_bytes()
    path.write_bytes(b"" if way == "empty" else data[: len(data) // 2])
    assert load_distance_field(env_map, grid) is None
    assert "unreadable" in caplog.text and DISTANCE_FIELD_FILE in caplog.text


@pytest.mark.parametrize("way", ["empty", "cut_short", "text"])
def test_corrupt_spatial_map_is_named(tmp_path: Path, way: str) -> None:
    from lampsam.localization.spatial_map import SpatialFeatureMap, SpatialMapError

    rng = np.random.default_rng(3)
    smap = SpatialFeatureMap(rng.normal(size=(4, 3)), rng.normal(size=(4, 128)).astype(np.float32),
                             np.ones(4), np.zeros(4), np.ones(4, dtype=np.int64))
    path = smap.save(tmp_path / "spatial_features.npz")
    assert len(SpatialFeatureMap.load(path)) == 4
    data = path.read_bytes()
    path.write_bytes({"empty": b"", "cut_short": data[: len(data) // 2],
                      "text": b"xyz: not an archive\n"}[way])
    with pytest.raises(SpatialMapError, match=r"spatial_features.npz: unreadable, not a NumPy"):
        SpatialFeatureMap.load(path)


def test_laser_log_on_a_map_of_another_sensor_warns(env_map: Path, tmp_path: Path,
                                                    caplog: pytest.LogCaptureFixture,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """A CARMEN log localized on a map whose grid came from another sensor used to fail its
    trials without a word on why; the sensor of the map is now named before computing."""
    lines = []
    for k in range(5):
        ranges = " ".join(f"{0.8 + 0.01 * ((b + k) % 7):.3f}" for b in range(180))
        t = 10.0 + 0.5 * k
        lines.append(f"FLASER 180 {ranges} {0.01 * k} 0.0 0.0 {0.01 * k} 0.0 0.0 {t} host {t}")
    log_path = tmp_path / "tiny.log"
    log_path.write_text("\n".join(lines) + "\n")
    rc = main(["localize", str(log_path), "--map", str(env_map), "--trials", "1",
               "--out", str(tmp_path / "L")])
    err = capsys.readouterr().err
    assert rc in (0, 1, 2) and "internal error" not in err
    assert f"{env_map} was built from test" in caplog.text
    assert "localizing a laser log on it" in caplog.text
