"""The README's "Python" example runs as written and gives a sensible estimate.

The code block is taken from README.md itself, so the documentation cannot drift
from the API.
"""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def python_section_code() -> str:
    """The first ```python block under the README's ``## Python`` heading."""
    text = README.read_text()
    start = text.index("\n## Python\n")
    end = text.find("\n## ", start + 1)
    section = text[start:end if end > 0 else None]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match, "README: no ```python block in the '## Python' section"
    return match.group(1)


@pytest.mark.slow
def test_readme_python_example_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(python_section_code(), str(README), "exec"), {"__name__": "readme"})
    printed = out.getvalue()
    # one line every 30 frames over 6 s at 15 Hz (frames 0, 30, 60, 90), then the summary
    assert len(re.findall(r"^t=", printed, re.M)) == 4, printed
    rms = re.search(r"position error RMS ([0-9.]+) mm", printed)
    assert rms, printed
    # 6 s of lab with lamps and corners: the smoother stays within a few mm; 30 mm
    # would mean the frontend or the backend is broken, not noise
    assert float(rms.group(1)) < 30.0, printed
    assert (tmp_path / "out/python/lab/rig.yaml").is_file()
