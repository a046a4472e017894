"""How honest a saved ceiling map's covariances are against the simulator's truth (NEES).

Usage::

    python scripts/bench/map_nees.py --truth RUN MAP [MAP ...]

``RUN`` is any simulated run of the same world (its ``landmarks.csv`` is the truth).
Each map landmark is paired with the nearest true landmark of its kind within 5 cm;
corners only when the localizer would use them (``LocalizeConfig.min_corner_obs`` sightings
and ``max_corner_sigma``). Printed per map and kind, NEES per dof over ``(x, y)``:

- ``marginal``: the landmark's error against its saved marginal covariance;
- ``conditional``: after the map frame's offset ``g`` is fitted to the paired errors
  (least squares on the frame model's gains ``C_l``), the residual against ``D_l``
  (:mod:`lampsam.backend.map_frame`), with the full 3-dof frame (``full``) and with the
  shift-only reduction the localizer uses (``shift``);

and, when ``map.yaml`` has it, the map's own pass-split figures
(:mod:`lampsam.backend.map_calibration`). NEES per dof 1 is honest, above 1 optimistic.
Figures: docs/ceiling-map.md.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling_map_io import CeilingMap, MapLandmark, read_map
from lampsam.backend.localize_only import LocalizeConfig
from lampsam.backend.map_frame import MapFrame, shift_only
from lampsam.datasets.logrun import read_run


def paired(cmap: CeilingMap, xyz: FloatArray, types: list[str], radius: float = 0.05
           ) -> list[tuple[MapLandmark, FloatArray]]:
    """``(landmark, true (x, y))`` of every map landmark with a true one of its kind within
    ``radius`` (corners: only those the localizer uses)."""
    loc = LocalizeConfig()
    out = []
    for lm in cmap.landmarks:
        if lm.kind == "corner" and (lm.n_obs < loc.min_corner_obs or math.sqrt(
                max(lm.cov[0, 0], lm.cov[1, 1])) > loc.max_corner_sigma):
            continue
        idx = np.flatnonzero([t.startswith(lm.kind) for t in types])
        if len(idx) == 0:
            continue
        d = np.linalg.norm(xyz[idx, :2] - lm.position[:2], axis=1)
        i = int(np.argmin(d))
        if d[i] <= radius:
            out.append((lm, xyz[idx[i], :2]))
    return out


def nees2(e: FloatArray, cov: FloatArray) -> float:
    """``e^T cov^-1 e / 2`` for a (2,) error."""
    return float(e @ np.linalg.solve(cov, e)) / 2.0


def conditional(pairs: list[tuple[MapLandmark, FloatArray]], frame: MapFrame
                ) -> tuple[FloatArray, dict[str, list[float]]]:
    """The fitted ``g`` and per kind the residual NEES per dof against ``D_l``."""
    a = np.vstack([frame.gains[lm.id][:2] for lm, _ in pairs])
    b = np.concatenate([t - lm.position[:2] for lm, t in pairs])
    g = np.linalg.lstsq(a, b, rcond=None)[0]
    out: dict[str, list[float]] = {"lamp": [], "corner": []}
    for lm, t in pairs:
        r = t - lm.position[:2] - frame.gains[lm.id][:2] @ g
        out[lm.kind].append(nees2(r, frame.conditional(lm.id, lm.cov)[:2, :2]))
    return g, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("maps", nargs="+", help="ceiling map folders (slam --save-map)")
    ap.add_argument("--truth", required=True, help="a simulated run of the same world")
    args = ap.parse_args()
    truth = read_run(args.truth).landmarks
    if truth is None:
        raise SystemExit(f"{args.truth}: no landmarks.csv (truth)")
    types = list(truth.types)
    print("| map | kind | paired | err RMS mm | marginal NEES/dof mean / median "
          "| conditional full mean / median | conditional shift mean / median | pass-split (map.yaml) |")
    print("|---|---|---:|---:|---|---|---|---|")
    for path in args.maps:
        cmap = read_map(path)
        pairs = paired(cmap, truth.xyz, types)
        cond = {}
        if cmap.frame is not None and len(pairs) >= 3:
            cond = {"full": conditional(pairs, cmap.frame)[1],
                    "shift": conditional(pairs, shift_only(cmap.frame))[1]}
        for kind in ("lamp", "corner"):
            rows = [(lm, t) for lm, t in pairs if lm.kind == kind]
            if not rows:
                continue
            err = np.array([t - lm.position[:2] for lm, t in rows])
            marg = [nees2(e, lm.cov[:2, :2]) for e, (lm, _) in zip(err, rows, strict=True)]
            cells = [f"{np.mean(c[kind]):.2f} / {np.median(c[kind]):.2f}" if c.get(kind) else "-"
                     for c in (cond.get("full", {}), cond.get("shift", {}))]
            cal = (cmap.calibration or {}).get(kind)
            split = (f"{cal['failed']} of {cal['landmarks_split']} failed, mean "
                     f"{cal['nees_mean']:.2f}, median {cal['nees_median']:.2f}, chi2/row "
                     f"{cal['chi2_per_row']:.2f}" if cal else "-")
            print(f"| {path} | {kind} | {len(rows)} | {1e3 * np.sqrt(np.mean(err**2)) * math.sqrt(2):.2f} "
                  f"| {np.mean(marg):.2f} / {np.median(marg):.2f} | {cells[0]} | {cells[1]} | {split} |")


if __name__ == "__main__":
    main()
