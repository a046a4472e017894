"""The comparison figures and the rendered report (no browser: the HTML is parsed)."""

from __future__ import annotations

import base64
import json
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from lampsam.evaluation import compare as C
from lampsam.evaluation import compare_plots as P
from lampsam.evaluation.compare_report import write_report


class _Page(HTMLParser):
    """Collects img sources, tags and text of an HTML page."""

    def __init__(self) -> None:
        super().__init__()
        self.imgs: list[str] = []
        self.tags: list[str] = []
        self.text: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append(tag)
        if tag == "img":
            self.imgs.append(dict(attrs).get("src") or "")

    def handle_data(self, data: str) -> None:
        self.text.append(data)


def _job_arrays(rng: np.random.Generator, bias: float) -> dict[str, np.ndarray]:
    """A straight 10 s drive with small errors, a 3x3 landmark grid, two lamps."""
    t = np.linspace(0.0, 10.0, 101)
    truth = np.column_stack([0.5 * t, np.ones_like(t), np.zeros_like(t)])
    poses = truth + np.column_stack([bias * t / 10, rng.normal(0, 0.002, (len(t), 2))])
    covs = np.tile(np.diag([1e-4, 1e-4, 1e-5]), (len(t), 1, 1))
    gx, gy = np.meshgrid([0.0, 2.0, 4.0], [0.0, 2.0, 4.0])
    true_xy = np.column_stack([gx.ravel(), gy.ravel()])
    true_type = np.array(["lamp", "lamp"] + ["corner"] * 7)
    lm_cov = np.tile(np.eye(2) * 1e-4, (9, 1, 1))
    lm_cov[8] = np.eye(2) * 1.0  # 3 sigma = 3 m: not drawn
    e = truth - poses
    return {"t": t, "poses": poses, "covs": covs, "t_err": t, "truth": truth,
            "pos_err": np.hypot(e[:, 0], e[:, 1]), "head_err": e[:, 2], "gt_xy": truth[:, :2],
            "nees": np.full(len(t), 3.0), "lm_xy": true_xy + 0.01, "lm_cov": lm_cov,
            "lm_type": true_type, "true_lm_xy": true_xy, "true_lm_type": true_type}


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("report")
    rng = np.random.default_rng(7)
    results = []
    for b, bias, rms in (("ekf", 0.05, 0.03), ("batch", 0.01, 0.01)):
        job = C.Job("lab", 0, str(out / "run"), b, str(out / "jobs" / b))
        Path(job.out_dir).mkdir(parents=True)
        path = Path(job.out_dir) / "arrays.npz"
        np.savez(path, **_job_arrays(rng, bias))
        results.append(C.JobResult(job, "ok", {"pos_rms_m": rms, "pos_max_m": 2 * rms}, str(path)))
    results.append(C.JobResult(C.Job("lab", 0, "r", "isam2", str(out / "jobs" / "isam2")),
                               "failed: indeterminate system"))
    figures = P.make_figures(out / "figures", results)
    write_report(out, C.aggregate(results), results, figures, 1.0)
    return out


def test_report_leads_with_errors_and_every_figure_has_a_caption(report_dir: Path) -> None:
    summary = json.loads((report_dir / "summary.json").read_text())
    names = [f["file"] for f in summary["figures"]]
    assert names[0] == "figures/lab_errors_time_distance.png"
    assert {"figures/lab_paths.png", "figures/lab_maps.png", "figures/lab_nees.png"} <= set(names)
    assert all(len(f["caption"]) > 30 for f in summary["figures"])
    md = (report_dir / "report.md").read_text()
    assert md.index("lab_errors_time_distance.png") < md.index("| run | backend |")
    assert "1 runs" not in md and "for 1 run)" in md


def test_html_renders_markdown_and_inlines_every_figure(report_dir: Path) -> None:
    html = (report_dir / "report.html").read_text()
    page = _Page()
    page.feed(html)
    text = "".join(page.text)
    assert "**" not in text and "![" not in text  # Markdown was rendered, not shown
    assert "strong" in page.tags and "table" in page.tags and "h1" in page.tags
    n_figs = len(json.loads((report_dir / "summary.json").read_text())["figures"])
    assert len(page.imgs) == n_figs
    for src in page.imgs:
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    assert "Failed jobs" in text and "indeterminate system" in text


def test_map_draws_only_readable_ellipses_at_the_given_limits() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = _job_arrays(np.random.default_rng(0), 0.0)
    d["lm_xy"][0] = (20.0, 20.0)  # far outside the limits
    fig, ax = plt.subplots()
    counts = P.plot_map(ax, d["lm_xy"], d["lm_cov"], d["lm_type"], d["true_lm_xy"],
                        d["true_lm_type"], limits=((-1.0, 5.0), (-1.0, 5.0)))
    assert counts == {"drawn": 8, "too_large": 1, "outside": 1}
    assert ax.get_xlim() == (-1.0, 5.0)
    labels = ax.get_legend_handles_labels()[1]
    assert "true lamp" in labels and "true corner" in labels  # distinct markers
    plt.close(fig)


def test_distance_and_major_sigma() -> None:
    xy = np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 5.0]])
    np.testing.assert_allclose(P.distance_travelled(xy), [0.0, 5.0, 6.0])
    rot = np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    cov = rot @ np.diag([0.04, 0.01]) @ rot.T
    np.testing.assert_allclose(P.major_sigma(cov[None]), [0.2], rtol=1e-12)
    assert np.isnan(P.major_sigma(np.full((1, 2, 2), np.nan))[0])
