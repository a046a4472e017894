"""Paper 2's Table 1 on the simulated office: a thin wrapper of ``lampsam table1``.

Usage::

    python scripts/table1_experiment.py --trials 50 --out out/table1 [--work /tmp/table1] [--jobs 2]
    python scripts/table1_experiment.py --out out/table1 --report-only

The experiment lives in :mod:`lampsam.evaluation.table1`; see docs/table1.md.
"""

from __future__ import annotations

import sys

from lampsam.cli import main

if __name__ == "__main__":
    raise SystemExit(main(["table1", *sys.argv[1:]]))
