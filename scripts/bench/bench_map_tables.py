"""Benchmark: building a laser map from the Intel log and loading its stored lookups.

Cases, median of ``--repeats`` runs each, wall and process CPU time (the machine is
shared, so wall time is inflated by others' load; ratios against a reference
measured in the same run are steadier):

* reference: reading the log (``read_carmen``);
* ``build-map --scans even`` without the range table (grid + distance field);
* the range table of that map's grid (``--max-range``, 360 bins): built
  (``build_range_table``, ``--build-repeats`` runs) against loaded from the stored
  file (``load_range_table``, which also checks the grid's fingerprint).

Map quality: the share of the odd (held-out) scans' endpoints that fall on an
occupied cell of the even-scan map (one cell of slack), and of the odd scans' poses
that lie in free cells.

Usage: ``.venv/bin/python scripts/bench/bench_map_tables.py [--repeats 3] [--build-repeats 2]``
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from scipy import ndimage
from timing import median_wall_cpu  # scripts/bench/timing.py, a sibling module

from lampsam.datasets.carmen import read_carmen, scan_endpoints
from lampsam.datasets.paths import shared_dataset
from lampsam.localization.grid import free_mask, occupied_mask
from lampsam.localization.map_build import build_map
from lampsam.localization.map_config import EnvMapConfig
from lampsam.localization.map_store import load_env_map
from lampsam.localization.map_tables import (
    TableConfig,
    build_range_table,
    load_range_table,
    save_range_table,
)


def main() -> None:
    """Run the cases and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--build-repeats", type=int, default=2)
    ap.add_argument("--max-range", type=float, default=4.5)
    args = ap.parse_args()
    root = shared_dataset("carmen")
    if root is None:
        raise SystemExit("shared dataset 'carmen' not found (set LAMPSAM_DATA)")
    log = root / "intel-corrected.log.gz"
    tmp = Path(tempfile.mkdtemp())
    cfg = EnvMapConfig(tables=TableConfig(range_table=False, laser_range_table=False))

    ref_w, ref_c = median_wall_cpu(lambda: read_carmen(log), args.repeats)
    map_w, map_c = median_wall_cpu(lambda: build_map(log, tmp / "map", config=cfg, scans="even"),
                         args.repeats)
    env = load_env_map(tmp / "map")
    grid = env.grid
    table = build_range_table(grid, args.max_range)
    size_mb = save_range_table(tmp / "map", grid, table).stat().st_size / 1e6
    tb_w, tb_c = median_wall_cpu(lambda: build_range_table(grid, args.max_range), args.build_repeats)
    tl_w, tl_c = median_wall_cpu(lambda: load_range_table(tmp / "map", grid, args.max_range),
                       args.repeats)

    print(f"{'case':<34}{'wall s':>9}{'cpu s':>9}{'x ref (wall)':>14}")
    for name, w, c in [("reference: read_carmen", ref_w, ref_c),
                       ("build-map --scans even (no table)", map_w, map_c),
                       (f"range table build ({args.max_range} m)", tb_w, tb_c),
                       ("range table load (stored)", tl_w, tl_c)]:
        print(f"{name:<34}{w:>9.3f}{c:>9.3f}{w / ref_w:>14.2f}")
    print(f"range table: {table.ranges_mm.shape[0] - 1} cells x {table.n_angles} bins, "
          f"{size_mb:.1f} MB on disk; load is {tb_w / tl_w:.0f}x faster than build (wall), "
          f"{tb_c / max(tl_c, 1e-9):.0f}x (CPU)")

    scans = read_carmen(log).scans
    odd = scans.subset(np.arange(1, len(scans), 2))
    occ = ndimage.binary_dilation(occupied_mask(grid))
    pts = scan_endpoints(odd)
    cells = grid.world_to_cell(pts)
    inside = grid.in_bounds(cells)
    hit = float(occ[cells[inside, 1], cells[inside, 0]].mean())
    pc = grid.world_to_cell(odd.poses[:, :2])
    free = free_mask(grid)
    in_free = float(free[pc[:, 1], pc[:, 0]].mean())
    layer = env.manifest["layers"]["grid"]
    print(f"map: {layer['size_cells']} cells of {grid.resolution} m from {layer['scans_used']} "
          f"of {layer['scans_selected']} even scans; odd scans' endpoints on occupied cells "
          f"(1 cell slack): {hit:.3f} of {int(inside.sum())}; odd poses in free cells: "
          f"{in_free:.3f} of {len(odd)}")


if __name__ == "__main__":
    main()
