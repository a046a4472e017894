"""The error base: messages name the file and line."""

from __future__ import annotations

from lampsam.errors import DatasetError, InputError, LampsamError


def test_input_error_names_file_and_line() -> None:
    err = DatasetError("time stamp goes backwards", path="run/odometry.csv", line=17)
    assert isinstance(err, InputError) and isinstance(err, LampsamError)
    assert str(err) == "run/odometry.csv:17: time stamp goes backwards"
    assert err.line == 17 and err.path is not None and err.path.name == "odometry.csv"


def test_missing_config_names_the_file(tmp_path) -> None:
    from lampsam.config_loader import read_table_file

    try:
        read_table_file(tmp_path / "absent.toml")
    except LampsamError as exc:
        assert "absent.toml" in str(exc)
    else:  # pragma: no cover - the call must raise
        raise AssertionError("missing config file did not raise")
