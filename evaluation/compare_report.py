"""The comparison report: ``report.md``, ``report.html`` and ``summary.json``.

The Markdown is the source; the HTML is rendered from it with the ``markdown``
library (tables extension) and made self-contained by inlining every figure as a
base64 PNG, so the one file can be mailed or archived. The report leads with the
figure of errors over time and distance, then the table, the plain-language
verdicts and the remaining figures, each with its one-line caption.
"""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lampsam.evaluation.compare import markdown_table
from lampsam.safe_io import write_json_atomic, write_text_atomic

if TYPE_CHECKING:
    from lampsam.evaluation.compare import Job, JobResult
    from lampsam.evaluation.compare_plots import SavedFigure

TITLE = "lampsam: EKF against smoothing"
CSS = (
    "body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;"
    "color:#222;line-height:1.45}"
    "table{border-collapse:collapse;font-size:0.85em;margin:1em 0}"
    "td,th{border:1px solid #bbb;padding:3px 7px;text-align:right}"
    "th{background:#f0f0f0}td:nth-child(-n+3){text-align:left}"
    "img{max-width:100%;border:1px solid #ddd}"
    "p.caption{font-style:italic;color:#444;margin-top:0.2em}"
)


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def consistency_sentences(rows: list[dict[str, Any]]) -> list[str]:
    """Plain-language verdicts on consistency and on smoother vs EKF accuracy (Markdown bullets)."""
    out = []
    for row in rows:
        if "nees_mean" not in row:
            continue
        lo, hi = row["nees_bounds"]
        verdict = ("overconfident" if row.get("nees_overconfident")
                   else "underconfident" if row.get("nees_underconfident") else "consistent")
        n_ok = row["seeds"] - row["failed"]
        out.append(
            f"- {row['run']} / {row['backend']}: time-averaged NEES {row['nees_mean']:.2f} "
            f"(ideal 3; per-step 95 % bounds [{lo:.2f}, {hi:.2f}] for {_plural(n_ok, 'run')}), "
            f"{row['nees_inside']:.0%} of steps inside: **{verdict}**"
            + (f", {row['nees_mean'] / 3.0:.1f}x the ideal" if verdict == "overconfident" else "")
            + "."
        )
    groups = sorted({r["run"] for r in rows})
    for g in groups:
        by = {r["backend"]: r for r in rows if r["run"] == g}
        if "ekf" in by and "pos_rms_m" in by["ekf"]:
            for b in ("batch", "isam2"):
                if b in by and "pos_rms_m" in by[b]:
                    ratio = by[b]["pos_rms_m"] / by["ekf"]["pos_rms_m"]
                    out.append(f"- {g}: {b} position RMS is {ratio:.2f}x the EKF's "
                               f"({by[b]['pos_rms_m']:.3f} m vs {by['ekf']['pos_rms_m']:.3f} m).")
    return out


def _figure_md(fig: SavedFigure) -> list[str]:
    """A figure and its caption in Markdown (image paragraph, then an italic caption line)."""
    return [f"![{fig.path.stem}](figures/{fig.path.name})", "", f"*{fig.caption}*", ""]


def report_markdown(rows: list[dict[str, Any]], results: list[JobResult],
                    figures: list[SavedFigure], wall_s: float,
                    unfinished: list[Job] | None = None) -> str:
    """The report in Markdown: lead figure, table, verdicts, failures, other figures.

    ``unfinished``: jobs an interrupt left unfinished; the report says which, and how
    to finish them (``--resume``).
    """
    n_seeds = sorted({r["seeds"] for r in rows})
    seeds_txt = (_plural(n_seeds[0], "seed") if len(n_seeds) == 1
                 else f"{'/'.join(str(s) for s in n_seeds)} seeds")
    md = [
        f"# {TITLE}",
        "",
        f"{_plural(len(results), 'job')} ({seeds_txt} per run and backend), wall time "
        f"{wall_s:.1f} s. Errors are without alignment (the start pose is known); RPE per metre "
        "from evo; NEES over (x, y, θ), averaged over seeds.",
        "",
    ]
    if unfinished:
        md += [f"**Interrupted: {_plural(len(unfinished), 'job')} not finished** "
               f"({', '.join(f'{j.group} seed {j.seed} / {j.backend}' for j in unfinished)}); "
               "`lampsam compare ... --resume` runs only those.", ""]
    if figures:
        md += _figure_md(figures[0])
    md += ["## Table", "", markdown_table(rows), "", "## Consistency and accuracy", "",
           *consistency_sentences(rows), ""]
    failures = [f"- {r.job.group} seed {r.job.seed} / {r.job.backend}: {r.status}"
                for r in results if r.status.startswith("failed")]
    if failures:
        md += ["## Failed jobs", "", *failures, ""]
    if len(figures) > 1:
        md += ["## More figures", ""]
        for f in figures[1:]:
            md += _figure_md(f)
    return "\n".join(md)


def markdown_to_html(md: str, base: Path, title: str = TITLE) -> str:
    """Render report Markdown to a self-contained HTML page (figures inlined as base64).

    Args:
        md: the Markdown text.
        base: directory that image paths in ``md`` are relative to.
        title: the page title.

    Raises:
        FileNotFoundError: an image the Markdown refers to does not exist.
    """
    import markdown

    body = markdown.markdown(md, extensions=["tables"], output_format="html")

    def inline(m: re.Match[str]) -> str:
        src = m.group(1)
        data = base64.b64encode((base / src).read_bytes()).decode("ascii")
        return f'src="data:image/png;base64,{data}"'

    body = re.sub(r'src="([^"]+\.png)"', inline, body)
    body = body.replace("<p><em>", '<p class="caption"><em>')
    return ("<!doctype html>\n<html lang='en'><head><meta charset='utf-8'>"
            f"<title>{html.escape(title)}</title><style>{CSS}</style></head>\n<body>\n"
            f"{body}\n</body></html>\n")


def write_report(out: Path, rows: list[dict[str, Any]], results: list[JobResult],
                 figures: list[SavedFigure], wall_s: float,
                 unfinished: list[Job] | None = None) -> None:
    """Write ``report.md``, ``report.html`` (rendered from it) and ``summary.json``.

    Each file is written atomically, ``summary.json`` last. ``unfinished``: jobs an
    interrupt left unfinished (named in the report and in ``summary.json``).
    """
    unfinished = unfinished or []
    md = report_markdown(rows, results, figures, wall_s, unfinished)
    write_text_atomic(out / "report.md", md)
    write_text_atomic(out / "report.html", markdown_to_html(md, out))
    summary = {
        "rows": rows,
        "jobs": [{"run": r.job.group, "seed": r.job.seed, "backend": r.job.backend,
                  "run_dir": r.job.run_dir, "status": r.status,
                  **{k: v for k, v in r.metrics.items() if k != "traceback"}} for r in results],
        "figures": [{"file": f"figures/{f.path.name}", "caption": f.caption} for f in figures],
        "wall_time_s": wall_s,
        "complete": not unfinished,
        "unfinished": [{"run": j.group, "seed": j.seed, "backend": j.backend} for j in unfinished],
    }
    write_json_atomic(out / "summary.json", summary)

