"""Drawing the environment map: grid, spatial features and ceiling features in one figure.

Plot functions take an ``ax`` and finished results and return the artists
(STYLE.md sec. 7); :func:`show_map` is the figure behind ``lampsam show-map``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.localization.grid import OccupancyGrid, free_mask, occupied_mask
from lampsam.localization.map_store import EnvironmentMap, load_env_map
from lampsam.safe_io import atomic_path

log = logging.getLogger(__name__)


def plot_grid(ax: Any, grid: OccupancyGrid) -> Any:
    """Draw the grid (occupied black, free white, unknown grey) in world metres.

    Args:
        ax: a matplotlib axes.
        grid: the map (axis-aligned origin assumed for drawing; yaw is ignored).

    Returns:
        The image artist.
    """
    img = np.full(grid.log_odds.shape, 0.8)
    img[free_mask(grid)] = 1.0
    img[occupied_mask(grid)] = 0.0
    x0, y0 = grid.origin[:2]
    extent = (x0, x0 + grid.width * grid.resolution, y0, y0 + grid.height * grid.resolution)
    return ax.imshow(
        img, cmap="gray", vmin=0, vmax=1, origin="lower", extent=extent, interpolation="nearest"
    )


def plot_spatial_features(ax: Any, xyz: np.ndarray, n_obs: np.ndarray | None = None) -> Any:
    """Spatial feature points projected to the floor, coloured by height.

    Args:
        ax: axes.
        xyz: (N, 3) world points, metres.
        n_obs: (N,) observations per point (marker size), or None.

    Returns:
        The scatter artist.
    """
    size = 8.0 if n_obs is None else 6.0 + 3.0 * np.sqrt(np.asarray(n_obs, float))
    return ax.scatter(
        xyz[:, 0],
        xyz[:, 1],
        c=xyz[:, 2],
        s=size,
        cmap="viridis",
        marker=".",
        linewidths=0,
        label="SIFT (colour = height)",
    )


def plot_ceiling_features(
    ax: Any, xyz: np.ndarray, is_lamp: np.ndarray, phi: np.ndarray | None = None
) -> list[Any]:
    """Ceiling lamps (yellow, with their axis) and corners (red crosses).

    Args:
        ax: axes.
        xyz: (L, 3) world positions, metres.
        is_lamp: (L,) bool.
        phi: (L,) lamp axes, rad (NaN for none), or None.

    Returns:
        The artists.
    """
    arts = [
        ax.scatter(
            xyz[is_lamp, 0],
            xyz[is_lamp, 1],
            s=60,
            c="gold",
            edgecolors="k",
            marker="o",
            label="lamps",
            zorder=3,
        ),
        ax.scatter(
            xyz[~is_lamp, 0],
            xyz[~is_lamp, 1],
            s=14,
            c="red",
            marker="x",
            label="ceiling corners" if np.any(~is_lamp) else None,
            zorder=3,
        ),
    ]
    if phi is not None:
        ok = is_lamp & np.isfinite(phi)
        dx, dy = 0.4 * np.cos(phi[ok]), 0.4 * np.sin(phi[ok])
        p = xyz[ok]
        segs = np.stack(
            [np.stack([p[:, 0] - dx, p[:, 1] - dy], 1), np.stack([p[:, 0] + dx, p[:, 1] + dy], 1)],
            1,
        )
        from matplotlib.collections import LineCollection

        lines = LineCollection(list(segs), colors="darkorange", linewidths=2, zorder=3)
        arts.append(ax.add_collection(lines))
    return arts


def plot_env_map(ax: Any, env: EnvironmentMap) -> list[Any]:
    """All three layers on one axes (grid underneath).

    Returns:
        The artists.
    """
    arts: list[Any] = [plot_grid(ax, env.grid)]
    if env.spatial is not None and len(env.spatial):
        arts.append(plot_spatial_features(ax, env.spatial.xyz, env.spatial.n_obs))
    if env.ceiling is not None and len(env.ceiling):
        arts += plot_ceiling_features(ax, env.ceiling.xyz, env.ceiling.is_lamp(), env.ceiling.phi)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    return arts


def show_map(map_dir: str | Path, out_png: str | Path, dpi: int = 150) -> Path:
    """Render a map directory to a PNG (``lampsam show-map``).

    Args:
        map_dir: directory written by ``build_map``.
        out_png: the image to write.
        dpi: resolution.

    Returns:
        ``out_png``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env = load_env_map(map_dir)
    fig, ax = plt.subplots(figsize=(9, 8))
    plot_env_map(ax, env)
    src = env.manifest.get("source", {})
    layers = env.manifest.get("layers", {})
    name = Path(str(src.get("path", map_dir))).name
    title = f"environment map: {name} ({src.get('kind', '?')}, poses {src.get('poses', '?')})"
    counts = []
    grid_layer = layers.get("grid", {})
    if "scans_used" in grid_layer:
        counts.append(f"{grid_layer['scans_used']} of {grid_layer.get('scans_total', '?')} scans "
                      f"({grid_layer.get('scans', 'all')})")
    if "spatial_features" in layers:
        counts.append(f"{layers['spatial_features']['count']} SIFT points")
    if "ceiling_features" in layers:
        counts.append(f"{layers['ceiling_features']['count']} ceiling features")
    ax.set_title(title + ("\n" + ", ".join(counts) if counts else ""), fontsize=10)
    if env.spatial is not None or env.ceiling is not None:
        ax.legend(loc="upper right", fontsize=8)
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    log.info("map figure written to %s", out_png)
    return out_png
