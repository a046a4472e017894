"""The one strict config loader: unknown keys, wrong types, nested tables, ranges.

Every error must name the file and the dotted key; through the CLI it must end
with exit code 2 and a one-line message on stderr, before any work is done.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from lampsam.backend.config import AssociationConfig, Isam2Config, SlamConfig
from lampsam.cli import main
from lampsam.config_loader import (
    ConfigError,
    FieldValueError,
    check_limits,
    from_mapping,
    limits,
    load_config,
    plain,
    read_table_file,
)


class _Colour(enum.Enum):
    RED = "red"
    BLUE = "blue"


@dataclass(frozen=True)
class _Inner:
    distance: float = field(default=1.0, metadata=limits(ge=0.0))
    count: int = field(default=3, metadata=limits(ge=1))
    band: tuple[float, float] = field(default=(0.1, 2.0), metadata=limits(gt=0.0))

    def __post_init__(self) -> None:
        check_limits(self)
        if self.band[1] <= self.band[0]:
            raise FieldValueError("band", "upper end must exceed lower end")


@dataclass(frozen=True)
class _Outer:
    name: str = "x"
    flag: bool = False
    colour: _Colour = _Colour.RED
    budget: int | None = 10
    inner: _Inner = field(default_factory=_Inner)
    names: tuple[str, ...] = ("a",)
    matrix: np.ndarray = field(default_factory=lambda: np.eye(2))


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


# --------------------------------------------------------------------------- the loader
def test_nested_partial_table_changes_only_given_keys() -> None:
    """A nested table sets its keys and keeps the other defaults; ints become floats."""
    cfg = from_mapping(_Outer, {"inner": {"distance": 2}, "colour": "blue", "budget": "none",
                                "matrix": [[1, 2], [3, 4]]}, source="a.toml")
    assert cfg.inner == _Inner(distance=2.0)
    assert isinstance(cfg.inner.distance, float)
    assert cfg.colour is _Colour.BLUE and cfg.budget is None and cfg.name == "x"
    np.testing.assert_array_equal(cfg.matrix, [[1.0, 2.0], [3.0, 4.0]])
    base = _Outer(name="base", inner=_Inner(count=7))
    cfg = from_mapping(_Outer, {"inner": {"distance": 0.5}}, base=base)
    assert cfg.name == "base" and cfg.inner == _Inner(distance=0.5, count=7)


def test_array_field_refuses_non_numeric_arrays() -> None:
    """An ``np.ndarray`` field goes through :func:`lampsam.strict_keys.finite_array`: an
    array of strings is a ConfigError naming the file and key (it was a bare ValueError
    from ``astype``), an array of bools is refused like a list of them, and a ragged or
    non-finite value reads as everywhere else."""
    for bad in (np.array(["a", "b"]), np.array([True, False]), [[1], [2, 3]], [1, math.nan]):
        with pytest.raises(ConfigError, match=r"^a\.toml: matrix: must be an array of finite "
                                              r"numbers, got "):
            from_mapping(_Outer, {"matrix": bad}, source="a.toml")


@pytest.mark.parametrize(
    ("data", "key", "words"),
    [
        ({"nmae": "y"}, "nmae", "did you mean 'name'"),
        ({"inner": {"distanse": 1.0}}, "inner.distanse", "unknown key"),
        ({"inner": {"distance": "far"}}, "inner.distance", "must be a number"),
        ({"inner": {"distance": True}}, "inner.distance", "must be a number, got a boolean"),
        ({"inner": {"distance": float("nan")}}, "inner.distance", "nan"),
        ({"inner": {"count": 2.0}}, "inner.count", "must be an integer"),
        ({"flag": 1}, "flag", "must be true or false"),
        ({"name": 3}, "name", "must be a string"),
        ({"colour": "green"}, "colour", "'red', 'blue'"),
        ({"budget": "ten"}, "budget", "must be an integer"),
        ({"inner": 5}, "inner", "must be a table"),
        ({"inner": {"band": [0.1]}}, "inner.band", "must have 2 elements"),
        ({"inner": {"band": [0.1, "x"]}}, "inner.band[1]", "must be a number"),
        ({"names": "abc"}, "names", "must be an array"),
        ({"matrix": [[1, 2], [3, float("inf")]]}, "matrix", "finite"),
        ({"inner": {"distance": -0.5}}, "inner.distance", "must be >= 0.0, got -0.5"),
        ({"inner": {"count": 0}}, "inner.count", "must be >= 1, got 0"),
        ({"inner": {"band": [-1.0, 2.0]}}, "inner.band", "element 0: must be > 0.0"),
        ({"inner": {"band": [2.0, 1.0]}}, "inner.band", "upper end must exceed"),
    ],
)
def test_bad_values_name_key_and_file(data: dict[str, object], key: str, words: str) -> None:
    """Each bad entry gives a ConfigError whose message is ``file: dotted.key: problem``."""
    with pytest.raises(ConfigError) as info:
        from_mapping(_Outer, data, source="settings.toml")
    msg = str(info.value)
    assert msg.startswith(f"settings.toml: {key}: "), msg
    assert words in msg, msg
    assert info.value.key == key


def test_python_construction_checks_ranges_too() -> None:
    """The ranges hold for objects built in Python (``__post_init__``), naming the field."""
    with pytest.raises(FieldValueError, match="keyframe_distance: must be >= 0.0, got -0.1"):
        Isam2Config(keyframe_distance=-0.1)
    with pytest.raises(FieldValueError, match="height_max"):
        AssociationConfig(height_min=2.0, height_max=1.0)
    with pytest.raises(FieldValueError, match="features"):
        SlamConfig(features=("lamps", "edges"))


def test_slam_config_from_toml_file(tmp_path: Path) -> None:
    """The slam/compare file format: top-level tables, strict, with the file named."""
    good = _write(tmp_path, "slam.toml", '[isam2]\nkeyframe_distance = 0\nevery_frame = true\n'
                                         '[association]\nmax_corner_updates = "none"\n'
                                         '[batch]\nhuber_k = 1\n')
    cfg = load_config(SlamConfig, good)
    assert cfg.isam2.keyframe_distance == 0.0 and cfg.isam2.every_frame
    assert cfg.association.max_corner_updates is None and cfg.batch.huber_k == 1.0
    assert cfg.ekf == SlamConfig().ekf
    bad = _write(tmp_path, "bad.toml", "[isam2]\nkeyframe_distance = -1\n")
    with pytest.raises(ConfigError, match=r"bad\.toml: isam2\.keyframe_distance: must be >= 0"):
        load_config(SlamConfig, bad)
    table = _write(tmp_path, "table.toml", "[isam3]\nx = 1\n")
    with pytest.raises(ConfigError, match=r"table\.toml: isam3: unknown table \(did you mean 'isam2'"):
        load_config(SlamConfig, table)


def test_yaml_and_table_selection(tmp_path: Path) -> None:
    """A YAML file works like TOML; a command's table is selected and others are errors."""
    path = _write(tmp_path, "c.yaml", "outer:\n  inner:\n    count: 4\n  budget: null\n")
    cfg = load_config(_Outer, path, table="outer")
    assert cfg.inner.count == 4 and cfg.budget is None
    path = _write(tmp_path, "d.yaml", "outer: {}\nother: {a: 1}\n")
    with pytest.raises(ConfigError, match=r"d\.yaml: other: unknown table \(this command reads \[outer\]\)"):
        load_config(_Outer, path, table="outer")
    assert load_config(_Outer, _write(tmp_path, "empty.yaml", ""), table="outer").inner == _Inner()


@pytest.mark.parametrize(
    ("name", "text", "words"),
    [
        ("broken.toml", "[isam2\n", "invalid TOML"),
        ("broken.yaml", "a: [1, 2\n", r"invalid YAML \(line \d+\)"),
        ("list.yaml", "- 1\n- 2\n", "the top level must be a table"),
        ("binary.toml", None, "not UTF-8"),
    ],
)
def test_unreadable_files(tmp_path: Path, name: str, text: str | None, words: str) -> None:
    """Parse errors and non-text files give a ConfigError naming the file."""
    path = tmp_path / name
    if text is None:
        path.write_bytes(b"\xff\xfe\x00bad")
    else:
        path.write_text(text)
    with pytest.raises(ConfigError, match=words) as info:
        read_table_file(path)
    assert str(info.value).startswith(str(path))
    with pytest.raises(ConfigError, match="not found"):
        read_table_file(tmp_path / "missing.toml")


@pytest.mark.parametrize(
    ("name", "text", "key", "words"),
    [
        ("inf.toml", "[isam2]\nkeyframe_distance = inf\n", "isam2.keyframe_distance",
         "must be finite, got inf"),
        ("minus.toml", "[ekf]\nsigma_start_xy = -inf\n", "ekf.sigma_start_xy", "must be finite, got -inf"),
        ("overflow.toml", "[batch]\nrelative_error_tol = 1e400\n", "batch.relative_error_tol",
         "must be finite, got inf"),
        ("nan.toml", "[ekf]\nvar_floor = nan\n", "ekf.var_floor", "must be a number, got nan"),
        ("inf.yaml", "association:\n  prune_sigma: .inf\n", "association.prune_sigma",
         "must be finite, got inf"),
        ("optional.toml", "[isam2]\ncorner_huber_k = inf\n", "isam2.corner_huber_k", "must be finite"),
        ("element.toml", "[reassociation]\nscales = [1.0, inf]\n", "reassociation.scales",
         "element 1: must be finite, got inf"),
        ("nolimits.toml", "[frontend.lamps]\nthin_width_px = inf\n", "frontend.lamps.thin_width_px",
         "must be finite, got inf"),
    ],
)
def test_infinite_and_nan_values_are_refused_by_key(
    tmp_path: Path, name: str, text: str, key: str, words: str
) -> None:
    """``inf`` (and ``-inf``, a TOML ``1e400`` that overflows to it, YAML ``.inf``) and
    ``nan`` are refused with the file and the dotted key, in a plain float, an optional
    float, an array element and a field that declares no limits."""
    from lampsam.frontend.pipeline import FrontendConfig

    path = _write(tmp_path, name, text)
    cls, table = (FrontendConfig, "frontend") if name == "nolimits.toml" else (SlamConfig, None)
    with pytest.raises(ConfigError) as info:
        load_config(cls, path, table=table)  # type: ignore[type-var]
    assert str(info.value) == f"{path}: {key}: {words}" or (
        str(info.value).startswith(f"{path}: {key}: ") and words in str(info.value)), info.value


def test_inf_where_it_means_never(tmp_path: Path) -> None:
    """Fields declared ``limits(finite=False)`` take ``inf``: iSAM2's relinearisation
    thresholds (never relinearise) and the re-association's ``switch`` (default inf);
    objects built in Python are held to the same rule."""
    path = _write(tmp_path, "never.toml", "[isam2]\nrelinearize_threshold = inf\n"
                                           "lamp_relinearize_threshold = inf\n"
                                           "[reassociation]\nswitch = inf\n")
    cfg = load_config(SlamConfig, path)
    assert cfg.isam2.relinearize_threshold == float("inf")
    assert cfg.isam2.lamp_relinearize_threshold == float("inf")
    assert cfg.reassociation.switch == float("inf") == SlamConfig().reassociation.switch
    with pytest.raises(FieldValueError, match="keyframe_distance: must be finite, got inf"):
        Isam2Config(keyframe_distance=float("inf"))


@pytest.mark.parametrize(
    ("name", "text", "words"),
    [
        ("key.toml", "[ekf]\nvar_floor = 1e-9\nvar_floor = 1e-8\n",
         "invalid TOML, line 3 ('var_floor = 1e-8', column 17): Cannot overwrite a value: "
         "a key or table given twice"),
        ("table.toml", "[ekf]\nvar_floor = 1e-9\n[isam2]\n[ekf]\n",
         "invalid TOML, line 4 ('[ekf]', column 5): Cannot declare ('ekf',) twice: "
         "a key or table given twice"),
        ("key.yaml", "ekf:\n  var_floor: 1.0e-9\n  var_floor: 1.0e-8\n",
         "invalid YAML (line 3): key 'var_floor' given twice (first on line 2)"),
        ("table.yaml", "ekf: {}\nisam2: {}\nekf:\n  var_floor: 1.0e-8\n",
         "invalid YAML (line 3): key 'ekf' given twice (first on line 1)"),
    ],
)
def test_key_or_table_given_twice(tmp_path: Path, name: str, text: str, words: str) -> None:
    """A key or table given twice is refused naming the file and the line (PyYAML alone
    keeps the last value silently)."""
    path = _write(tmp_path, name, text)
    with pytest.raises(ConfigError) as info:
        load_config(SlamConfig, path)
    assert str(info.value) == f"{path}: {words}"


def test_yaml_merge_keys_still_override(tmp_path: Path) -> None:
    """YAML merge keys (``<<``) are not repeated keys: an explicit key overrides a merged one."""
    path = _write(tmp_path, "merge.yaml", "base: &b {var_floor: 1.0e-9, update_iterations: 2}\n")
    doc = read_table_file(path)
    assert doc["base"]["update_iterations"] == 2
    from lampsam.config_loader import parse_yaml

    assert parse_yaml("a: &a {x: 1, y: 2}\nb:\n  <<: *a\n  y: 3\n")["b"] == {"x": 1, "y": 3}


@pytest.mark.parametrize(
    ("text", "key", "words"),
    [
        ("[isam2.relinearize_threshold]\nx = 1\n", "isam2.relinearize_threshold",
         "must be a number, got a table"),
        ("[ekf]\nupdate_iterations = { n = 2 }\n", "ekf.update_iterations",
         "must be an integer, got a table"),
        ("isam2 = 0.1\n", "isam2", "must be a table, got a float"),
        ("[isam3]\nx = 1\n", "isam3", "unknown table (did you mean 'isam2'?)"),
        ("[isam2.extra]\nx = 1\n", "isam2.extra", "unknown table"),
    ],
)
def test_table_where_a_value_belongs_and_unknown_tables(
    tmp_path: Path, text: str, key: str, words: str
) -> None:
    """A table given for a value, a value for a table and an unknown table are each
    refused naming the dotted key."""
    path = _write(tmp_path, "cfg.toml", text)
    with pytest.raises(ConfigError) as info:
        load_config(SlamConfig, path)
    assert str(info.value).startswith(f"{path}: {key}: ") and words in str(info.value), info.value


def test_plain_numbers() -> None:
    """Numbers in messages print as plain numbers, never ``np.float64(...)``."""
    assert plain(np.float64(5.0)) == "5.0"
    assert plain(np.int64(3)) == "3"
    assert plain(np.bool_(True)) == "True"
    assert plain(2.5) == "2.5"


# --------------------------------------------------------------------------- every command
@pytest.mark.parametrize(
    ("argv", "text", "key"),
    [
        (["slam", "RUN", "--out", "OUT"], "[isam2]\nkeyframe_distance = -1\n", "isam2.keyframe_distance"),
        (["slam", "RUN", "--out", "OUT"], "[isam2]\nkeyframe_distance = \"far\"\n", "isam2.keyframe_distance"),
        (["compare", "lab", "--out", "OUT"], "[ekf]\nvar_flor = 1e-9\n", "ekf.var_flor"),
        (["build-map", "RUN", "--out", "OUT"], "[envmap.depth]\nresolution = \"fine\"\n",
         "envmap.depth.resolution"),
        (["build-map", "RUN", "--out", "OUT"], "[envmap]\nfeature_every = 1\n[envmp]\n", "envmp"),
        (["localize", "RUN", "--map", "MAP", "--out", "OUT"],
         "[localize.filter]\nparticles_per_candidat = 10\n", "localize.filter.particles_per_candidat"),
        (["localize", "RUN", "--map", "MAP", "--out", "OUT"], "[localize]\nmode = \"best\"\n",
         "localize.mode"),
        (["stereo", "RUN", "--estimator", "ekf", "--out", "OUT"], "[stereo]\ngate_chi2 = true\n",
         "stereo.gate_chi2"),
        (["kinect-sim", "office", "--out", "OUT"], "[kinect]\nwidth = 320.5\n", "kinect.width"),
        (["frontend-eval", "RUN"], "[frontend.lamps]\nno_such_key = 1\n", "frontend.lamps.no_such_key"),
        (["slam", "RUN", "--out", "OUT"], "[isam2]\nkeyframe_angle = inf\n", "isam2.keyframe_angle"),
        (["stereo", "RUN", "--estimator", "ekf", "--out", "OUT"], "[stereo]\nmin_depth = inf\n",
         "stereo.min_depth"),
    ],
)
def test_cli_config_errors_name_key_and_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], text: str, key: str
) -> None:
    """Each command with ``--config`` rejects a bad file with exit 2, naming file and key,
    before reading its inputs (RUN, MAP do not exist here) or writing anything."""
    cfg = _write(tmp_path, "cfg.toml", text)
    out = tmp_path / "out"
    args = [str(out) if a == "OUT" else str(tmp_path / a) if a in ("RUN", "MAP") else a
            for a in argv]
    assert main([*args, "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert f"{cfg}: {key}: " in err, err
    assert not out.exists()


def test_localize_nested_filter_table_is_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A nested ``[localize] filter = {...}`` table (an AttributeError before) is accepted:
    the command goes on to its inputs and fails on the missing run, not on the config."""
    cfg = _write(tmp_path, "loc.toml", "[localize]\nmode = \"ours\"\n"
                                       "filter = { particles_per_candidate = 50 }\n")
    code = main(["localize", str(tmp_path / "norun"), "--map", str(tmp_path / "nomap"),
                 "--out", str(tmp_path / "out"), "--config", str(cfg)])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "loc.toml" not in err and ("norun" in err or "nomap" in err), err
