"""A static, self-contained HTML report over one or more run directories.

The page holds: a summary table (R@100P, AUC, counts, speed), the precision-recall curves of
every run on one plot, and per run the similarity matrix beside the ground truth (as the
paper's Fig. 9, with the accepted detections marked right / wrong), the per-stage timing table,
how many frames ended in each status, and the run's match pictures. Every image is a PNG
embedded as base64, so the file can be mailed or archived alone.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, StableCuesError
from ..groundtruth import GroundTruth, fit_view, load_ground_truth
from ..runs import Run
from .evaluate import evaluate_run, run_evaluations
from .plots import figure_png, new_figure, plot_matrix, plot_pr_curves, plot_status_counts

logger = logging.getLogger(__name__)

_CSS = """
body { font-family: system-ui, sans-serif; margin: 24px; color: #222; max-width: 1400px; }
h1 { font-size: 1.5em; }
h2 { font-size: 1.25em; border-bottom: 1px solid #ccc; padding-bottom: 4px; margin-top: 2em; }
h3 { font-size: 1.05em; margin-top: 1.4em; }
table { border-collapse: collapse; margin: 8px 0 16px 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 4px 8px; text-align: right; }
th { background: #f0f0f0; } td.l, th.l { text-align: left; }
img { max-width: 100%; border: 1px solid #ddd; margin: 4px 0; }
.note { color: #666; font-size: 0.85em; } .warn { color: #a40; }
.matches figure { display: inline-block; margin: 4px 12px 4px 0; vertical-align: top; }
.matches img { max-width: 560px; }
"""


def _img_tag(png: bytes, alt: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return html.escape(str(value))


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]], left: int = 1) -> str:
    head = "".join(
        f'<th class="{"l" if i < left else ""}">{html.escape(h)}</th>' for i, h in enumerate(header)
    )
    body = "".join(
        "<tr>"
        + "".join(f'<td class="{"l" if i < left else ""}">{_fmt(v)}</td>' for i, v in enumerate(r))
        + "</tr>"
        for r in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def choose_evaluation(
    run: Run, protocol: str | None = None, tolerance: int | None = None
) -> dict[str, Any] | None:
    """The run's evaluation to show: matching ``protocol`` / ``tolerance`` when given, else the
    exact protocol's, else the first one; None when the run has not been evaluated."""
    evals = list(run_evaluations(run).values())
    if protocol is not None:
        evals = [e for e in evals if e.get("protocol") == protocol]
    if tolerance is not None:
        evals = [e for e in evals if int(e.get("tolerance") or 0) == tolerance]
    if not evals:
        return None
    exact = [e for e in evals if e.get("protocol") == "exact"]
    return (exact or evals)[0]


def _load_gt(
    doc: dict[str, Any], cache: dict[tuple[str, str], GroundTruth]
) -> tuple[GroundTruth | None, str]:
    path = doc.get("gt_file")
    if not path:
        return None, "the evaluation names no ground-truth file"
    key = (str(path), str(doc.get("gt_view", "all")))
    if key not in cache:
        try:
            notes = doc.get("gt_notes") or {}
            raw = load_ground_truth(
                path,
                variable=doc.get("gt_variable") if str(path).endswith((".mat", ".npz")) else None,
                n_ref=notes.get("n_ref"),
            )
            frames = doc.get("gt_frames")
            cache[key] = fit_view(raw, doc.get("gt_view", "all"), int(frames) if frames is not None else None)
        except StableCuesError as exc:
            logger.warning("ground truth not shown: %s", exc)
            return None, f"ground truth not shown: {exc}"
    gt = cache[key]
    if doc.get("gt_sha256") and gt.sha256 != doc["gt_sha256"]:
        return gt, f"warning: {path} changed since the evaluation (SHA-256 differs)"
    return gt, ""


def build_report(
    runs: Sequence[Run],
    out: str | Path,
    *,
    protocol: str | None = None,
    tolerance: int | None = None,
    title: str = "stablecues loop-closure evaluation",
    max_matches: int = 6,
) -> Path:
    """Write the HTML report for ``runs`` to ``out``.

    Args:
        runs: loaded run directories (evaluated with ``stablecues eval`` for curves and counts).
        out: the HTML file to write.
        protocol: show evaluations of this protocol (default: exact when present).
        tolerance: and of this tolerance.
        title: page title.
        max_matches: match pictures shown per run.

    Returns:
        The written path.
    """
    out_path = Path(out)
    gt_cache: dict[tuple[str, str], GroundTruth] = {}
    if protocol is None and tolerance is None:
        protocol, tolerance = _common_protocol(runs)
    docs = [choose_evaluation(r, protocol, tolerance) for r in runs]
    _check_one_protocol(runs, docs)
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p class='note'>Generated {_dt.datetime.now(_dt.UTC).isoformat(timespec='seconds')}. "
        "R@100P: recall at 100 % precision, swept over every distinct score. AUC: step-wise area under "
        "the precision-recall curve. Counts at the detector's own decisions.</p>",
    ]
    parts += _summary_section(runs, docs)
    parts += _pr_section(runs, docs)
    for run, doc in zip(runs, docs, strict=True):
        parts += _run_section(run, doc, gt_cache, max_matches)
    parts.append("</body></html>")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text("\n".join(parts), encoding="utf-8")
    return out_path


def _common_protocol(runs: Sequence[Run]) -> tuple[str | None, int | None]:
    """A (protocol, tolerance) every evaluated run has, exact first; (None, None) when none."""
    kinds = [
        {(str(e["protocol"]), int(e.get("tolerance") or 0)) for e in run_evaluations(r).values()}
        for r in runs
    ]
    kinds = [k for k in kinds if k]
    common = set.intersection(*kinds) if kinds else set()
    if not common:
        return None, None
    return ("exact", 0) if ("exact", 0) in common else sorted(common)[0]


def _check_one_protocol(runs: Sequence[Run], docs: Sequence[dict[str, Any] | None]) -> None:
    """Raise when the evaluations shown were made under different protocols or tolerances: one
    table and one plot would compare figures that do not compare.

    Raises:
        ConfigError: naming each run's protocol.
    """
    shown = {(d["protocol"], int(d.get("tolerance") or 0)) for d in docs if d is not None}
    if len(shown) > 1:
        each = ", ".join(
            f"{r.name}: {d['protocol']} +-{int(d.get('tolerance') or 0)}"
            for r, d in zip(runs, docs, strict=True)
            if d is not None
        )
        raise ConfigError(
            f"the runs were evaluated under different protocols ({each}); choose one with "
            "--protocol and --tolerance"
        )


def _summary_section(runs: Sequence[Run], docs: Sequence[dict[str, Any] | None]) -> list[str]:
    """The summary table: one row per run, its evaluation's counts, R@100P, AUC and speed."""
    rows = []
    for run, doc in zip(runs, docs, strict=True):
        total = (run.timings().get("total") or {}).get("mean")
        if doc is None:
            rows.append([run.name, run.meta.get("preset"), "not evaluated", *["-"] * 10, total])
            continue
        gt_name = Path(doc["gt_file"]).name if doc.get("gt_file") else "-"
        rows.append(
            [
                run.name,
                run.meta.get("preset"),
                doc["protocol"],
                doc.get("tolerance"),
                doc.get("exclude"),
                f"{gt_name} ({str(doc.get('gt_sha256') or '')[:12]})",
                doc.get("queries"),
                doc["positives"],
                doc["tp"],
                doc["fp"],
                doc["fn"],
                f"{100 * doc['recall_at_100p']:.2f} %",
                float(doc["auc"]),
                total,
            ]
        )
    header = ["run", "preset", "protocol", "tol", "excl", "ground truth (sha256)", "queries", "positives"]
    header += ["TP", "FP", "FN", "R@100P", "AUC", "ms/frame"]
    return ["<h2>Summary</h2>", _table(header, rows, left=3)]


def _pr_section(runs: Sequence[Run], docs: Sequence[dict[str, Any] | None]) -> list[str]:
    """The precision-recall curves of every evaluated run on one plot."""
    curves = [
        (
            f"{run.name} (R@100P {100 * doc['recall_at_100p']:.1f} %, AUC {doc['auc']:.3f})",
            np.asarray(doc["pr_curve"]["recall"]),
            np.asarray(doc["pr_curve"]["precision"]),
        )
        for run, doc in zip(runs, docs, strict=True)
        if doc is not None and "pr_curve" in doc
    ]
    parts = ["<h2>Precision-recall</h2>"]
    if curves:
        fig, (ax,) = new_figure(7.0, 5.0)
        plot_pr_curves(ax, curves)
        parts.append(_img_tag(figure_png(fig), "precision-recall curves"))
    else:
        parts.append("<p class='note'>No run has been evaluated: run <code>stablecues eval</code> first.</p>")
    return parts


def _run_section(
    run: Run, doc: dict[str, Any] | None, gt_cache: dict[tuple[str, str], GroundTruth], max_matches: int
) -> list[str]:
    """One run: what was run, similarity and ground truth, stage times, statuses, match pictures."""
    meta: list[list[Any]] = [
        ["dataset", run.meta.get("dataset")],
        ["format", run.meta.get("format")],
        ["preset", run.meta.get("preset")],
        ["frames", len(run)],
        ["complete", "yes" if run.complete else "no (interrupted)"],
    ]
    for key in ("semantics", "score_column"):  # recorded by stablecues run / demo
        if run.meta.get(key):
            meta.append([key.replace("_", " "), run.meta[key]])
    trows = [
        [k, v.get("mean"), v.get("std"), v.get("min"), v.get("max"), v.get("count")]
        for k, v in run.timings().items()
    ]
    return [
        f"<h2>Run {html.escape(run.name)}</h2>",
        _table(["", ""], meta, left=2),
        _matrices_section(run, doc, gt_cache),
        "<h3>Time per stage (ms)</h3>",
        _table(["stage", "mean", "std", "min", "max", "frames"], trows),
        *_status_section(run),
        *_matches_section(run, max_matches),
    ]


def _status_section(run: Run) -> list[str]:
    """How many frames ended in each status, as a table and a bar plot (nothing for an empty run)."""
    counts = run.status_counts()
    if not counts:
        return []
    fig, (ax,) = new_figure(5.5, 0.4 + 0.3 * len(counts))
    plot_status_counts(ax, counts)
    return [
        "<h3>Decisions per status</h3>",
        "<p class='note'>The stage that decided each frame: how many frames each stage rejected.</p>",
        _table(["status", "frames", "share"], [[k, v, v / len(run)] for k, v in counts.items()]),
        _img_tag(figure_png(fig), "status counts"),
    ]


def _matches_section(run: Run, max_matches: int) -> list[str]:
    """Up to ``max_matches`` of the run's match pictures, with their names as captions."""
    pictures = run.matches[:max_matches]
    if not pictures:
        return []
    parts = [f"<h3>Match pictures ({len(pictures)} of {len(run.matches)})</h3><div class='matches'>"]
    for p in pictures:
        caption = f"<figcaption>{html.escape(p.stem)}</figcaption>"
        parts.append(f"<figure>{_img_tag(p.read_bytes(), p.stem)}{caption}</figure>")
    parts.append("</div>")
    return parts


def _matrices_section(run: Run, doc: dict[str, Any] | None, cache: dict[tuple[str, str], GroundTruth]) -> str:
    sim = run.similarity
    gt, note = (None, "") if doc is None else _load_gt(doc, cache)
    if sim is None and gt is None:
        out = "<p class='note'>No similarity matrix and no ground truth to show.</p>"
        return out + (f"<p class='warn'>{html.escape(note)}</p>" if note else "")
    panels = (sim is not None) + (gt is not None)
    fig, axes = new_figure(5.5 * panels, 5.0, ncols=panels)
    k = 0
    if sim is not None:
        plot_matrix(axes[k], sim, "similarity (BoW score)", cmap="magma", colorbar=True)
        k += 1
    if gt is not None and doc is not None:
        points: list[tuple[np.ndarray, np.ndarray, str, str]] = []
        try:
            ev, _ = evaluate_run(
                run,
                gt,
                protocol=doc["protocol"],
                tolerance=int(doc.get("tolerance", 0)),
                exclude=int(doc.get("exclude", 0)),
                exclude_s=float(doc.get("exclude_s") or 0.0),
                detections=doc.get("detections_used", "accepted"),
                score=doc.get("score_column", "score"),
            )
            cand = dict(zip(run.frames.tolist(), run.candidates.tolist(), strict=True))
            rows = ev.detection_frames
            cols = np.array([cand[int(r)] for r in rows], dtype=np.int64)
            points = [
                (rows[ev.correct], cols[ev.correct], "#2ca02c", "detection, right"),
                (rows[~ev.correct], cols[~ev.correct], "#d62728", "detection, wrong"),
            ]
        except StableCuesError as exc:
            note = f"{note} detections not overlaid: {exc}".strip()
        plot_matrix(
            axes[k],
            gt.matrix,
            f"ground truth ({gt.path.name if gt.path else 'in memory'})",
            cmap="Greys",
            points=points,
        )
    html_out = "<h3>Similarity and ground truth</h3>" + _img_tag(
        figure_png(fig), "similarity and ground truth"
    )
    if note:
        html_out += f"<p class='warn'>{html.escape(note)}</p>"
    return html_out
