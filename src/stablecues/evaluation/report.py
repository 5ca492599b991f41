"""A static HTML report over one or more run directories.

The page holds: a summary table (R@100P, AUC, counts, loops accepted, speed), the
precision-recall curves of every run (the whole curves, and a zoom on where they crowd near
precision 1), and per run: what was run, the loss funnel (for each positive query, the stage
where its true loop was lost), the similarity matrix beside the ground truth (as the paper's
Fig. 9, with the detections marked true / false), every accepted loop as a thumbnail marked
true or false with the verifier that accepted it (click to enlarge, then browse with previous /
next), how many frames ended in each status, and the per-stage timing table.

The plots are PNGs embedded in the page. The loop pictures are JPEG files in a folder beside
it, ``<page stem>_files/`` (linked relatively: keep the page and the folder together); each is
the run's own match picture of that loop where ``stablecues run`` kept one, else the two frames
side by side, read from the run's dataset. The page has no script and loads nothing from a
network: clicking a picture shows it large through a CSS ``:target`` overlay.
"""

from __future__ import annotations

import datetime as _dt
import html
import logging
import os
import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np

from ..errors import ConfigError, StableCuesError, reason
from ..groundtruth import GroundTruth, fit_view, load_ground_truth
from ..outputs import check_output, write_output
from ..runs import Run
from .evaluate import evaluate_run, evaluation_funnel, run_evaluations
from .funnel import Funnel
from .metrics import Evaluation
from .plots import (
    Overlay,
    figure_png,
    new_figure,
    plot_funnel,
    plot_matrix,
    plot_pr_curves,
    plot_status_counts,
    report_style,
)

logger = logging.getLogger(__name__)

THUMBNAIL_WIDTH = 360
"""Width in pixels of the loop thumbnails."""

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", "DejaVu Sans", sans-serif; font-size: 16px;
       line-height: 1.45; color: #222; max-width: 1400px; margin: 24px auto; padding: 0 24px; }
h1 { font-size: 1.75em; margin-bottom: 0.2em; }
h2 { font-size: 1.45em; border-bottom: 2px solid #ccc; padding-bottom: 4px; margin-top: 2.2em; }
h3 { font-size: 1.2em; margin-top: 1.6em; }
table { border-collapse: collapse; margin: 8px 0 16px 0; font-size: 0.95em; }
th, td { border: 1px solid #ccc; padding: 4px 10px; text-align: right; }
th { background: #f0f0f0; } td.l, th.l { text-align: left; }
img.plot { max-width: 100%; height: auto; border: 1px solid #ddd; margin: 4px 0; }
.note { color: #555; font-size: 0.95em; max-width: 75em; } .warn { color: #a40; }
nav.toc { font-size: 0.95em; } nav.toc li { margin: 2px 0; }
.mark { font-weight: bold; padding: 1px 7px; border-radius: 4px; color: #fff; white-space: nowrap; }
.mark.true { background: #1a7f37; } .mark.false { background: #c62828; }
.mark.unscored, .mark.unknown { background: #6d6d6d; }
.loops { display: grid; grid-template-columns: repeat(auto-fill, minmax(300px, 1fr)); gap: 14px; }
.loop { margin: 0; border: 3px solid #bbb; border-radius: 6px; padding: 6px; background: #fafafa; }
.loop.true { border-color: #1a7f37; } .loop.false { border-color: #c62828; background: #fff4f4; }
.loop img { width: 100%; height: auto; display: block; }
.loop figcaption { font-size: 0.92em; margin-top: 5px; }
.loop .nopic { color: #666; font-size: 0.9em; padding: 18px 6px; background: #eee; text-align: center; }
.lightbox { display: none; }
.lightbox:target { display: flex; position: fixed; inset: 0; z-index: 10; background: rgba(0, 0, 0, 0.9);
                   flex-direction: column; align-items: center; justify-content: center; color: #eee; }
.lightbox img { max-width: 96vw; max-height: 80vh; }
.lightbox p { max-width: 90vw; text-align: center; margin: 8px; }
.lightbox a { color: #8cf; } .lightbox .note { color: #ccc; }
.lightbox nav a { margin: 0 1.2em; font-size: 1.1em; }
"""

STAGE_TEXT = {
    "excluded": "nothing could be proposed (no frame outside the exclusion window, no database result)",
    "not_retrieved": "no true loop among the database results",
    "below_alpha": "true loops retrieved, but in no island above alpha",
    "wrong_island": "a true island passed alpha, but another island was verified",
    "temporal": "the true island was there, but temporal consistency stopped the frame",
    "geometry": "the true loop was verified and rejected, and nothing else was accepted",
    "wrong_accepted": "a wrong loop was accepted instead",
    "below_threshold": "the true loop was accepted, below the 100 %-precision threshold",
    "found": "accepted above that threshold: counted in the recall at 100 % precision",
    "unknown": "the run kept no record of the stages (written before extra.jsonl held them)",
}
"""What each stage of the loss funnel (:mod:`.funnel`) means, in words for the page."""

_VERDICT_WORD = {"true": "true", "false": "false", "unscored": "not scored", "unknown": "no ground truth"}
_VERDICT_BGR = {"true": (55, 127, 26), "false": (40, 40, 198), "unscored": (109, 109, 109),
                "unknown": (109, 109, 109)}
_PICTURE_RE = re.compile(r"^loop_(\d+)_(\d+)$")


def _img_tag(png: bytes, alt: str) -> str:
    import base64

    data = base64.b64encode(png).decode("ascii")
    return f'<img class="plot" alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


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


@dataclass
class _Shown:
    """What the page shows of one run's evaluation: the document, and what re-evaluating it
    against its ground truth gives (the true / false marks, the funnel of older files)."""

    doc: dict[str, Any] | None
    gt: GroundTruth | None = None
    note: str = ""
    ev: Evaluation | None = None
    funnel: Funnel | None = None

    @property
    def correct(self) -> dict[int, bool]:
        """Query frame -> whether its detection is a true loop (scored detections only)."""
        if self.ev is None:
            return {}
        return dict(zip(self.ev.detection_frames.tolist(), self.ev.correct.tolist(), strict=True))


def _analyse(run: Run, doc: dict[str, Any] | None, cache: dict[tuple[str, str], GroundTruth]) -> _Shown:
    if doc is None:
        return _Shown(None)
    gt, note = _load_gt(doc, cache)
    shown = _Shown(doc, gt, note, funnel=evaluation_funnel(doc))
    if gt is None:
        return shown
    try:
        shown.ev, again = evaluate_run(
            run,
            gt,
            protocol=doc["protocol"],
            tolerance=int(doc.get("tolerance") or 0),
            exclude=int(doc.get("exclude") or 0),
            exclude_s=float(doc.get("exclude_s") or 0.0),
            detections=doc.get("detections_used", "accepted"),
            score=doc.get("score_column", "score"),
        )
    except StableCuesError as exc:
        shown.note = f"{note} detections not marked true / false: {exc}".strip()
        return shown
    if shown.funnel is None:
        shown.funnel = evaluation_funnel(again)
    return shown


class _Pictures:
    """The folder beside the page that holds the loop pictures (created when the first is written).

    Files are written afresh: a file or symbolic link already at a picture's name is removed
    first, never written through, and a folder that is a symbolic link is refused.
    """

    def __init__(self, page: Path) -> None:
        self.root = page.with_name(page.stem + "_files")
        if self.root.is_symlink():
            raise ConfigError(f"{self.root}: the report's picture folder is a symbolic link (not followed)")

    def write(self, sub: str, name: str, data: bytes) -> str:
        """Write ``<root>/<sub>/<name>``; returns its URL relative to the page."""
        folder = self.root / sub
        try:
            if folder.is_symlink():
                raise ConfigError(f"{folder}: the report's picture folder is a symbolic link (not followed)")
            folder.mkdir(parents=True, exist_ok=True)
            path = folder / name
            path.unlink(missing_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
        except OSError as exc:
            raise ConfigError(f"{folder / name}: cannot write the report's picture ({reason(exc)})") from None
        return f"{quote(self.root.name)}/{quote(sub)}/{quote(name)}"


def build_report(
    runs: Sequence[Run],
    out: str | Path,
    *,
    protocol: str | None = None,
    tolerance: int | None = None,
    title: str = "stablecues loop-closure evaluation",
    max_loops: int | None = None,
) -> Path:
    """Write the HTML report for ``runs`` to ``out`` (and its loop pictures beside it).

    Args:
        runs: loaded run directories (evaluated with ``stablecues eval`` for curves, counts,
            true / false marks and the loss funnel).
        out: the HTML file to write; the pictures go to ``<stem>_files/`` beside it.
        protocol: show evaluations of this protocol (default: exact when present).
        tolerance: and of this tolerance.
        title: page title.
        max_loops: accepted loops per run that get a picture (spread evenly over the run;
            None: every one). Every accepted loop is listed either way.

    Returns:
        The written path.

    Raises:
        ConfigError: runs evaluated under different protocols, a negative ``max_loops``, or a
            picture that cannot be written.
    """
    if max_loops is not None and max_loops < 0:
        raise ConfigError(f"max_loops: expected a number >= 0 or None, got {max_loops}")
    out_path = Path(out)
    gt_cache: dict[tuple[str, str], GroundTruth] = {}
    if protocol is None and tolerance is None:
        protocol, tolerance = _common_protocol(runs)
    docs = [choose_evaluation(r, protocol, tolerance) for r in runs]
    _check_one_protocol(runs, docs)
    unevaluated = {id(r): _not_evaluated(r, protocol, tolerance) for r, d in zip(runs, docs, strict=True)
                   if d is None}
    for r in runs:
        if id(r) in unevaluated:
            logger.warning("%s: %s; the report shows its decisions but no TP / FP / R@100P (run "
                           "`stablecues eval %s` first)", r.path, unevaluated[id(r)], r.path)
    shown = [_analyse(r, d, gt_cache) for r, d in zip(runs, docs, strict=True)]
    check_output(out_path, "report", make_folder=True)  # before any figure is drawn
    pictures = _Pictures(out_path)
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>",
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p class='note'>Generated {_dt.datetime.now(_dt.UTC).isoformat(timespec='seconds')}. "
        "R@100P: recall at 100 % precision, swept over every distinct score. AUC: step-wise area under "
        "the precision-recall curve. Counts at the detector's own decisions.</p>",
        _contents(runs, shown),
    ]
    with report_style():
        parts += _summary_section(runs, docs, unevaluated)
        parts += _pr_section(runs, docs)
        for k, (run, s) in enumerate(zip(runs, shown, strict=True), 1):
            parts += _run_section(k, run, s, pictures, max_loops)
    parts.append("</body></html>")
    write_output(out_path, "\n".join(parts), "report")
    return out_path


def _contents(runs: Sequence[Run], shown: Sequence[_Shown]) -> str:
    items = ["<li><a href='#summary'>Summary</a></li>", "<li><a href='#pr'>Precision-recall</a></li>"]
    for k, (run, s) in enumerate(zip(runs, shown, strict=True), 1):
        links = [f"<a href='#r{k}'>Run {html.escape(run.name)}</a>"]
        if s.funnel is not None:
            links.append(f"<a href='#r{k}-funnel'>loss funnel</a>")
        links.append(f"<a href='#r{k}-loops'>accepted loops ({int(np.count_nonzero(run.accepted))})</a>")
        items.append("<li>" + " · ".join(links) + "</li>")
    return f"<nav class='toc'><ul>{''.join(items)}</ul></nav>"


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


def _not_evaluated(run: Run, protocol: str | None, tolerance: int | None) -> str:
    """Why a run has no evaluation to show: none at all, or none under the one asked for."""
    others = sorted({f"{e.get('protocol')} +-{int(e.get('tolerance') or 0)}"
                     for e in run_evaluations(run).values()})
    if not others:
        return "not evaluated"
    asked = " ".join(x for x in (protocol, None if tolerance is None else f"+-{tolerance}") if x)
    return f"not evaluated under {asked or 'the protocol shown'} (only {', '.join(others)})"


def _summary_section(runs: Sequence[Run], docs: Sequence[dict[str, Any] | None],
                     unevaluated: dict[int, str]) -> list[str]:
    """The summary table: one row per run, its evaluation's counts, R@100P, AUC and speed (the
    first frame's warm-up apart)."""
    rows = []
    for run, doc in zip(runs, docs, strict=True):
        total = (run.timings().get("total") or {}).get("mean")
        accepted = int(np.count_nonzero(run.accepted))
        if doc is None:
            rows.append([run.name, run.meta.get("preset"), unevaluated[id(run)], *["-"] * 6, accepted,
                         *["-"] * 4, total])
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
                accepted,
                doc["tp"],
                doc["fp"],
                doc["fn"],
                f"{100 * doc['recall_at_100p']:.2f} %",
                float(doc["auc"]),
                total,
            ]
        )
    header = ["run", "preset", "protocol", "tol", "excl", "ground truth (sha256)", "queries", "positives"]
    header += ["loops accepted", "TP", "FP", "FN", "R@100P", "AUC", "ms/frame (1st apart)"]
    losses = _losses_paragraph(runs, docs)
    return ["<section id='summary'><h2>Summary</h2>", _table(header, rows, left=3), *losses, "</section>"]


#: what losing a true loop at each stage of the funnel means, for the summary's paragraph
_LOSS_WORDS = {
    "excluded": "had nothing outside the exclusion window to compare with",
    "not_retrieved": "never had their place among the database's results (appearance too different for "
                     "the vocabulary)",
    "below_alpha": "were retrieved but scored under alpha",
    "wrong_island": "had their place retrieved but not among the islands verified (other places "
                    "scored higher, or the island's best entry was a few frames off)",
    "temporal": "were stopped by the temporal window",
    "geometry": "had their place verified and rejected by the geometry (or refused as under "
                "min_confidence)",
    "wrong_accepted": "had a wrong place accepted instead",
    "below_threshold": "were found, but less confident than the most confident false loop (so not "
                       "counted at 100 % precision)",
}


def _losses_paragraph(runs: Sequence[Run], docs: Sequence[dict[str, Any] | None]) -> list[str]:
    """One paragraph: for each evaluated run, how many loops it found at 100 % precision and
    where its loss funnel says it lost the others, largest loss first."""
    sentences = []
    for run, doc in zip(runs, docs, strict=True):
        funnel = evaluation_funnel(doc) if doc is not None else None
        if funnel is None or funnel.positives == 0:
            continue
        lost = sorted(((n, stage) for stage, n in funnel.counts.items()
                       if n and stage in _LOSS_WORDS), reverse=True)
        parts = [f"{n} {_LOSS_WORDS[stage]}" for n, stage in lost[:3]]
        found = funnel.counts.get("found", 0)
        text = (f"<b>{html.escape(run.name)}</b> found {found} of {funnel.positives} loops at 100 % "
                "precision" + ("; of the others, " + "; ".join(parts) if parts else "") + ".")
        sentences.append(text)
    if not sentences:
        return []
    return ["<p class='note'>Where the loops were lost (each run's loss funnel, below): "
            + " ".join(sentences) + "</p>"]


def _pr_section(runs: Sequence[Run], docs: Sequence[dict[str, Any] | None]) -> list[str]:
    """The precision-recall curves of every evaluated run: the whole curves and a zoom."""
    curves = [
        (
            f"{run.name} (R@100P {100 * doc['recall_at_100p']:.1f} %, AUC {doc['auc']:.3f})",
            np.asarray(doc["pr_curve"]["recall"]),
            np.asarray(doc["pr_curve"]["precision"]),
        )
        for run, doc in zip(runs, docs, strict=True)
        if doc is not None and "pr_curve" in doc
    ]
    parts = ["<section id='pr'><h2>Precision-recall</h2>"]
    if not curves:
        parts.append("<p class='note'>No run has been evaluated: run <code>stablecues eval</code> first.</p>")
        return [*parts, "</section>"]
    fig, axes = new_figure(13.0, 5.6, ncols=2)
    plot_pr_curves(axes[0], curves)
    plot_pr_curves(axes[1], curves, zoom=True)
    parts += [
        "<p class='note'>Left the whole curves, right a zoom on where they are. Each run has its own "
        "colour and dash pattern; where curves coincide the first run is drawn widest and each later "
        "one narrower on top of it, so a shared stretch shows as nested bands. The marker on the "
        "precision = 1 line is where each run reaches its recall at 100 % precision.</p>",
        _img_tag(figure_png(fig), "precision-recall curves, whole and zoomed"),
        "</section>",
    ]
    return parts


def _run_section(k: int, run: Run, shown: _Shown, pictures: _Pictures, max_loops: int | None) -> list[str]:
    """One run: what was run, funnel, similarity and ground truth, accepted loops, statuses, times."""
    meta: list[list[Any]] = [
        ["dataset", run.meta.get("dataset")],
        ["format", run.meta.get("format")],
        ["preset", run.meta.get("preset")],
        ["frames", len(run)],
        ["complete", "yes" if run.complete else "no (interrupted)"],
        ["verifier (configured)", _configured_verifier(run) or "none: BoW score only"],
    ]
    for key in ("semantics", "score_column"):  # recorded by stablecues run / demo
        if run.meta.get(key):
            meta.append([key.replace("_", " "), run.meta[key]])
    timings = run.timings()
    trows = [
        [name, v.get("mean"), v.get("std"), v.get("min"), v.get("max"), v.get("count"), v.get("first")]
        for name, v in timings.items()
    ]
    return [
        f"<h2 id='r{k}'>Run {html.escape(run.name)}</h2>",
        _table(["run", "value"], meta, left=2),
        *_funnel_section(k, shown),
        _matrices_section(run, shown),
        *_loops_section(k, run, shown, pictures, max_loops),
        *_status_section(run),
        "<h3>Time per stage (ms)</h3>",
        *(["<p class='note'>The first frame loads the models and compiled code: its time is given "
           "apart and left out of the other figures.</p>"]
          if any(v.get("first") is not None for v in timings.values()) else []),
        _table(["stage", "mean", "std", "min", "max", "frames", "first frame"], trows),
    ]


def _funnel_section(k: int, shown: _Shown) -> list[str]:
    """The loss funnel of the evaluation: a table with each stage in words, and a bar plot."""
    doc, funnel = shown.doc, shown.funnel
    if doc is None:
        return []
    head = f"<h3 id='r{k}-funnel'>Loss funnel: where each positive query lost its true loop</h3>"
    if funnel is None:
        return [head, "<p class='note'>This evaluation was written before the funnel was kept, and its "
                "ground truth could not be read to compute it: run <code>stablecues eval</code> again.</p>"]
    total = funnel.positives
    rows = [[stage, STAGE_TEXT.get(stage, ""), n, f"{n / total:.1%}" if total else "-"]
            for stage, n in funnel.counts.items()]
    rows.append(["positive queries", "queries with an eligible loop in the ground truth", total, ""])
    parts = [head, "<p class='note'>For every query that has a loop in the ground truth, the first "
             "stage of the pipeline its true loop did not pass (in pipeline order).</p>",
             _table(["stage", "meaning", "queries", "share"], rows, left=2)]
    wrong = funnel.counts.get("wrong_accepted", 0)
    if doc.get("detections_used", "accepted") == "accepted" and int(doc["fp"]) > wrong:
        parts.append(f"<p class='note'>Besides these, {int(doc['fp']) - wrong} loop(s) were accepted on "
                     "queries that have no loop in the ground truth (false positives the funnel does "
                     "not hold).</p>")
    if total:
        fig, (ax,) = new_figure(9.0, 0.9 + 0.36 * len(funnel.counts))
        plot_funnel(ax, funnel.counts)
        parts.append(_img_tag(figure_png(fig), "loss funnel"))
    return parts


def _status_section(run: Run) -> list[str]:
    """How many frames ended in each status, as a table and a bar plot (nothing for an empty run)."""
    counts = run.status_counts()
    if not counts:
        return []
    fig, (ax,) = new_figure(8.0, 0.9 + 0.36 * len(counts))
    plot_status_counts(ax, counts)
    return [
        "<h3>Decisions per status</h3>",
        "<p class='note'>The stage that decided each frame: how many frames each stage rejected.</p>",
        _table(["status", "frames", "share"], [[k, v, v / len(run)] for k, v in counts.items()]),
        _img_tag(figure_png(fig), "status counts"),
    ]


def _matrices_section(run: Run, shown: _Shown) -> str:
    sim, gt, note, ev = run.similarity, shown.gt, shown.note, shown.ev
    if sim is None and gt is None:
        out = "<p class='note'>No similarity matrix and no ground truth to show.</p>"
        return out + (f"<p class='warn'>{html.escape(note)}</p>" if note else "")
    panels = (sim is not None) + (gt is not None)
    fig, axes = new_figure(6.4 * panels, 6.0, ncols=panels)
    if sim is not None:
        plot_matrix(axes[0], sim, "similarity", cmap="magma", colorbar=True,
                    colorbar_label="BoW score")
    if gt is not None:
        points: list[Overlay] = []
        if ev is not None:
            cand = dict(zip(run.frames.tolist(), run.candidates.tolist(), strict=True))
            rows = ev.detection_frames
            cols = np.array([cand[int(r)] for r in rows], dtype=np.int64)
            points = [
                Overlay(rows[ev.correct], cols[ev.correct], "#1a9850", "true detection", "o"),
                Overlay(rows[~ev.correct], cols[~ev.correct], "#d62728", "false detection", "x"),
            ]
        plot_matrix(axes[-1], gt.matrix, f"ground truth ({gt.path.name if gt.path else 'in memory'})",
                    cmap="Greys", points=points)
    html_out = "<h3>Similarity and ground truth</h3>" + _img_tag(
        figure_png(fig), "similarity and ground truth"
    )
    if note:
        html_out += f"<p class='warn'>{html.escape(note)}</p>"
    return html_out


@dataclass(frozen=True)
class _Loop:
    """One accepted loop as the page lists it."""

    frame: int
    candidate: int
    score: float
    verdict: str  # "true", "false", "unscored" (not a query of the evaluation), "unknown" (no ground truth)
    verifier: str
    detail: str  # the verifier's reason ("3 of 10 triangles agree ...")
    truth: str  # the ground truth's loops of the frame, in words ("" without ground truth)
    stage: str  # the funnel's stage of the frame ("" when it is no positive query)

    @property
    def label(self) -> str:
        return f"frame {self.frame} \u2192 {self.candidate}"


def _configured_verifier(run: Run) -> str | None:
    cfg = run.config.get("verification")
    if isinstance(cfg, dict) and isinstance(cfg.get("method"), str):
        return str(cfg["method"])
    return None


def _verifier(extra: dict[str, Any], configured: str | None) -> tuple[str, str]:
    """(the verifier that decided, its reason) from a frame's ``extra.jsonl`` record."""
    method = extra.get("verifier")
    detail = extra.get("reason") if isinstance(extra.get("reason"), str) else ""
    if isinstance(method, str):
        name = method if configured in (None, method) else f"{method} (stood in for {configured})"
        return name, str(detail)
    if configured is None:
        return "none: BoW score only", ""
    return f"{configured} (configured; not recorded per frame)", ""


def _ranges(frames: np.ndarray, most: int = 4) -> str:
    """Frame numbers as ranges: [3, 4, 5, 9] -> "3-5, 9"."""
    if frames.size == 0:
        return ""
    breaks = np.flatnonzero(np.diff(frames) > 1)
    starts = np.r_[frames[0], frames[breaks + 1]]
    ends = np.r_[frames[breaks], frames[-1]]
    pairs = zip(starts.tolist(), ends.tolist(), strict=True)
    parts = [f"{a}" if a == b else f"{a}\u2013{b}" for a, b in pairs]
    return ", ".join(parts[:most]) + (", \u2026" if len(parts) > most else "")


def _accepted_loops(run: Run, shown: _Shown) -> list[_Loop]:
    """Every loop the run accepted, in frame order, with its verdict against the ground truth."""
    extras: dict[int, dict[str, Any]] = {}
    for e in run.extra():
        if isinstance(e, dict) and isinstance(e.get("frame"), int):
            extras[int(e["frame"])] = e
    correct = shown.correct
    configured = _configured_verifier(run)
    stages = shown.funnel.rows if shown.funnel is not None else {}
    tol = int((shown.doc or {}).get("tolerance") or 0)
    tolerated = f" (the protocol tolerates \u00b1{tol} frames)" if tol else ""
    loops = []
    for k in np.flatnonzero(run.accepted):
        frame, cand = int(run.frames[k]), int(run.candidates[k])
        if shown.ev is None:
            verdict = "unknown"
        elif frame in correct:
            verdict = "true" if correct[frame] else "false"
        else:
            verdict = "unscored"
        truth = ""
        if shown.gt is not None and frame < shown.gt.n:
            found = _ranges(np.flatnonzero(shown.gt.matrix[frame]))
            truth = f"ground truth of frame {frame}: " + (f"loops with {found}" if found else "no loop")
            truth += tolerated
        name, detail = _verifier(extras.get(frame, {}), configured)
        loops.append(_Loop(frame, cand, float(run.scores[k]), verdict, name, detail, truth,
                           stages.get(frame, "")))
    return loops


def _loops_section(k: int, run: Run, shown: _Shown, pictures: _Pictures, max_loops: int | None) -> list[str]:
    """Every accepted loop: a thumbnail marked true / false, the verifier, click to enlarge."""
    loops = _accepted_loops(run, shown)
    head = f"<h3 id='r{k}-loops'>Accepted loops ({len(loops)})</h3>"
    if not loops:
        return [head, "<p class='note'>The run accepted no loop.</p>"]
    verdicts = Counter(loop.verdict for loop in loops)
    by_verifier = Counter(loop.verifier for loop in loops)
    marks = ", ".join(f"{n} {_VERDICT_WORD[v]}" for v, n in sorted(verdicts.items()))
    doc = shown.doc or {}
    protocol = ""
    if shown.ev is not None:
        tol = int(doc.get("tolerance") or 0)
        protocol = f" (ground truth, protocol {doc.get('protocol')}" + (f" \u00b1{tol})" if tol else ")")
    verifiers = ", ".join(f"{name} {n}" for name, n in by_verifier.most_common())
    parts = [head, f"<p class='note'>{html.escape(marks + protocol)}. Verified by: {html.escape(verifiers)}. "
             "Click a picture to enlarge it, then browse with previous / next.</p>"]
    if shown.note:
        parts.append(f"<p class='warn'>{html.escape(shown.note)}</p>")
    urls, why = _loop_pictures(k, run, loops, pictures, max_loops)
    if why:
        parts.append(f"<p class='note'>{html.escape(why)}</p>")
    parts.append("<div class='loops'>")
    parts += [_loop_card(k, loop, urls.get(loop.frame)) for loop in loops]
    parts.append("</div>")
    with_pictures = [loop for loop in loops if loop.frame in urls]
    for n, loop in enumerate(with_pictures):
        prev = with_pictures[n - 1].frame if n > 0 else None
        nxt = with_pictures[n + 1].frame if n + 1 < len(with_pictures) else None
        parts.append(_lightbox(k, loop, urls[loop.frame][1], prev, nxt))
    return parts


_TICK = {"true": "\u2713 ", "false": "\u2717 "}
_DOT = " \u00b7 "


def _caption(loop: _Loop) -> str:
    score = f"score {loop.score:.4g}" if np.isfinite(loop.score) else "no score"
    tick = _TICK.get(loop.verdict, "")
    detail = f" \u2014 {html.escape(loop.detail)}" if loop.detail else ""
    lines = [
        f"<span class='mark {loop.verdict}'>{tick}{html.escape(_VERDICT_WORD[loop.verdict])}</span> "
        f"<b>{html.escape(loop.label)}</b>{_DOT}{score}",
        f"verifier: <b>{html.escape(loop.verifier)}</b>{detail}",
    ]
    extra = _DOT.join(t for t in (loop.truth, f"funnel: {loop.stage}" if loop.stage else "") if t)
    if extra:
        lines.append(f"<span class='note'>{html.escape(extra)}</span>")
    return "<br>".join(lines)


def _loop_card(k: int, loop: _Loop, urls: tuple[str, str] | None) -> str:
    if urls is None:
        picture = "<div class='nopic'>no picture</div>"
    else:
        picture = (f"<a href='#r{k}-view-{loop.frame}'><img src='{html.escape(urls[0])}' "
                   f"alt='{html.escape(loop.label)}'></a>")
    return (f"<figure class='loop {loop.verdict}' id='r{k}-loop-{loop.frame}' data-query='{loop.frame}' "
            f"data-candidate='{loop.candidate}' data-verdict='{loop.verdict}'>{picture}"
            f"<figcaption>{_caption(loop)}</figcaption></figure>")


def _lightbox(k: int, loop: _Loop, url: str, prev: int | None, nxt: int | None) -> str:
    back = f"#r{k}-loop-{loop.frame}"
    nav = [f"<a href='#r{k}-view-{prev}'>\u2039 previous</a>" if prev is not None else "",
           f"<a href='{back}'>close \u2715</a>",
           f"<a href='#r{k}-view-{nxt}'>next \u203a</a>" if nxt is not None else ""]
    img = f"<img loading='lazy' src='{html.escape(url)}' alt='{html.escape(loop.label)}'>"
    return (f"<div class='lightbox' id='r{k}-view-{loop.frame}'><nav>{''.join(nav)}</nav>"
            f"<a href='{back}'>{img}</a>"
            f"<p>{_caption(loop)}</p></div>")


def _loop_pictures(
    k: int, run: Run, loops: Sequence[_Loop], pictures: _Pictures, max_loops: int | None
) -> tuple[dict[int, tuple[str, str]], str]:
    """Write the loops' pictures (thumbnail and full size); returns (frame -> (thumbnail URL,
    full URL), why some loops have none, or "")."""
    chosen = list(loops)
    if max_loops is not None and len(loops) > max_loops:
        picks = np.linspace(0, len(loops) - 1, max_loops).round().astype(int).tolist()
        chosen = [loops[i] for i in sorted(set(picks))]
    stored: dict[tuple[int, int], Path] = {}
    for p in run.matches:
        m = _PICTURE_RE.match(p.stem)
        if m:
            stored[(int(m[1]), int(m[2]))] = p
    urls: dict[int, tuple[str, str]] = {}
    problems: list[str] = []
    dataset = _LazyDataset(run)
    for loop in chosen:
        image, problem = _loop_image(loop, stored.get((loop.frame, loop.candidate)), dataset)
        if image is None:
            problems.append(problem)
            continue
        full, thumb = _stamp(image, loop)
        name = f"loop_{loop.frame:05d}_{loop.candidate:05d}"
        urls[loop.frame] = (pictures.write(f"run{k}", f"{name}_thumb.jpg", thumb),
                            pictures.write(f"run{k}", f"{name}.jpg", full))
    why = ""
    if len(chosen) < len(loops):
        why = f"Pictures of {len(chosen)} loops spread over the run (max_loops); the others are listed."
    if problems:
        why = f"{why} {len(problems)} loop(s) without a picture: {problems[0]}".strip()
    return urls, why


class _LazyDataset:
    """The run's dataset, opened on first use (only loops without a stored picture need it)."""

    def __init__(self, run: Run) -> None:
        self.run = run
        self.dataset: Any = None
        self.problem = ""
        self.tried = False

    def frame_image(self, index: int) -> np.ndarray:
        if not self.tried:
            self.tried = True
            self.dataset, self.problem = _open_dataset(self.run)
        if self.dataset is None:
            raise _NoPicture(self.problem)
        return np.asarray(self.dataset[index].image)


class _NoPicture(Exception):
    """No frame can be read: the dataset is not there (the message says why)."""


def _open_dataset(run: Run) -> tuple[Any, str]:
    """(the run's dataset as ``stablecues run`` opened it, "") or (None, why not)."""
    path, fmt = run.meta.get("dataset"), run.meta.get("format") or "auto"
    if not isinstance(path, str) or not isinstance(fmt, str):
        return None, f"{run.path}: meta.json names no dataset to read the frames from"
    try:
        from ..datasets import open_dataset

        dataset = open_dataset(path, format=fmt)
        n = run.meta_int("dataset_frames")
    except StableCuesError as exc:
        return None, f"the run's dataset was not opened ({exc})"
    except OSError as exc:
        return None, f"the run's dataset was not opened ({reason(exc)})"
    if n is not None and len(dataset) != n:
        return None, f"the dataset {path} now has {len(dataset)} frames, the run's had {n}"
    return dataset, ""


def _loop_image(loop: _Loop, stored: Path | None, dataset: _LazyDataset) -> tuple[np.ndarray | None, str]:
    """(H, W, 3) uint8 BGR picture of a loop: the run's match picture, else the two frames side
    by side; or (None, why not)."""
    from ..imageio import read_image

    if stored is not None:
        try:
            return read_image(stored, "bgr"), ""
        except StableCuesError as exc:
            logger.warning("match picture not shown: %s", exc)
    try:
        query, cand = dataset.frame_image(loop.frame), dataset.frame_image(loop.candidate)
    except _NoPicture as exc:
        return None, str(exc)
    except (StableCuesError, IndexError, OSError) as exc:
        return None, f"frames {loop.frame} and {loop.candidate} not read ({exc})"
    from ..verification.plot import side_by_side

    canvas, _ = side_by_side(query, cand)
    return np.ascontiguousarray(canvas[:, :, ::-1]), ""


def _stamp(image: np.ndarray, loop: _Loop) -> tuple[bytes, bytes]:
    """The picture with a banner naming the verdict and the frames, in the verdict's colour, as
    (full-size JPEG, thumbnail JPEG)."""
    import cv2

    colour = _VERDICT_BGR[loop.verdict]
    bar = max(26, min(60, image.shape[1] // 28))
    out = cv2.copyMakeBorder(image, bar, 5, 5, 5, cv2.BORDER_CONSTANT, value=colour)
    word = {"true": "TRUE LOOP", "false": "FALSE LOOP"}.get(loop.verdict, _VERDICT_WORD[loop.verdict].upper())
    text = f"{word}  frame {loop.frame} -> {loop.candidate}  ({loop.verifier})"
    font = cv2.FONT_HERSHEY_SIMPLEX
    scale = bar / 34
    width = cv2.getTextSize(text, font, scale, max(1, round(scale * 2)))[0][0]
    if width > out.shape[1] - 20:  # a narrow picture: smaller letters, the text still fits
        scale *= (out.shape[1] - 20) / width
    cv2.putText(out, text, (10, int(bar * 0.72)), font, scale, (255, 255, 255), max(1, round(scale * 2)),
                cv2.LINE_AA)
    small_h = max(1, round(out.shape[0] * THUMBNAIL_WIDTH / out.shape[1]))
    thumb = cv2.resize(out, (THUMBNAIL_WIDTH, small_h), interpolation=cv2.INTER_AREA)
    quality = [cv2.IMWRITE_JPEG_QUALITY, 88]
    ok_full, full = cv2.imencode(".jpg", out, quality)
    ok_thumb, small = cv2.imencode(".jpg", thumb, quality)
    if not (ok_full and ok_thumb):
        raise ConfigError(f"loop {loop.label}: the picture could not be encoded as JPEG")
    return full.tobytes(), small.tobytes()
