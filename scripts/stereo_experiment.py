"""Paper 3's stereo two-point experiment: a thin wrapper of ``lampsam stereo-experiment``.

Usage::

    python scripts/stereo_experiment.py --out out/stereo [--seeds 20] [--no-kitti]

The experiment lives in :mod:`lampsam.evaluation.stereo_experiment`; see docs/stereo.md.
"""

from __future__ import annotations

import sys

from lampsam.cli import main

if __name__ == "__main__":
    raise SystemExit(main(["stereo-experiment", *sys.argv[1:]]))
