"""``python -m lampsam``: the same entry point as the ``lampsam`` command."""

from lampsam.cli import main

raise SystemExit(main())
