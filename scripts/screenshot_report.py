"""Screenshot an HTML report in headless Chromium, to check how it renders.

    python scripts/screenshot_report.py out/demo/compare/report.html --out /tmp/report.png

Needs Debian's ``chromium`` (``apt-get install -y chromium``; not part of CI). The
browser runs without network, sync or component updates, in a throw-away profile,
so the screenshot shows only the file (the report inlines its figures). Prints the
PNG path; exit code 2 when Chromium is missing or fails.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars"]


def screenshot(html: Path, png: Path, width: int = 1280, height: int = 6000,
               browser: str | None = None, timeout_s: float = 120.0) -> Path:
    """Render ``html`` in headless Chromium and save a ``width`` x ``height`` px screenshot.

    Raises:
        FileNotFoundError: no Chromium on PATH, or the HTML file is missing.
        RuntimeError: Chromium exits without writing the PNG.
    """
    exe = browser or shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        raise FileNotFoundError("chromium not found on PATH (apt-get install -y chromium)")
    if not html.is_file():
        raise FileNotFoundError(f"{html}: no such file")
    png.parent.mkdir(parents=True, exist_ok=True)
    png.unlink(missing_ok=True)
    with tempfile.TemporaryDirectory(prefix="lampsam-chromium-") as profile:
        cmd = [exe, *FLAGS, f"--user-data-dir={profile}", f"--screenshot={png.resolve()}",
               f"--window-size={width},{height}", html.resolve().as_uri()]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    if not png.is_file():
        raise RuntimeError(f"chromium wrote no screenshot (exit {proc.returncode}): "
                           f"{proc.stderr.strip()[-500:]}")
    return png


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("html", type=Path, help="the HTML file (e.g. report.html)")
    ap.add_argument("--out", type=Path, required=True, help="PNG to write")
    ap.add_argument("--width", type=int, default=1280, help="window width, px (default 1280)")
    ap.add_argument("--height", type=int, default=6000, help="window height, px (default 6000)")
    args = ap.parse_args()
    try:
        print(screenshot(args.html, args.out, args.width, args.height))
    except (FileNotFoundError, RuntimeError, subprocess.TimeoutExpired) as exc:
        print(f"screenshot_report: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
