"""The dataset report: ``batch_report.json`` and a self-contained ``batch_report.html``.

The JSON is the record (``mvviz view --batch DIR`` reads it): one row per job (scene
and setting) with its figures (:func:`pipeline.batch.jobs.summarize`), status, error,
results file and the command that opens it in the viewer; the worst scenes, the worst
moments across the dataset, and per sweep setting the mean of each metric over scenes.
The HTML shows the same as tables and inline SVG plots (matplotlib, base64 data URIs,
the text kept as text): nothing is fetched when it is opened.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
import os
import shlex
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from pipeline.core.files import SceneFormatError, atomic_write  # noqa: E402

REPORT_JSON = "batch_report.json"
REPORT_HTML = "batch_report.html"
REPORT_VERSION = 1
# metric -> (column title, higher is better); the order of the tables' columns
METRICS = {
    "mpjpe_mm": ("MPJPE mm", False),
    "pck160": ("PCK@160", True),
    "pcp": ("PCP", True),
    "accel_mm": ("accel err mm/f²", False),
    "smpl_mpjpe_mm": ("SMPL MPJPE mm", False),
    "assoc_precision": ("assoc P", True),
    "assoc_recall": ("assoc R", True),
    "id_switches": ("ID switches", False),
    "reprojection_mean_px": ("reproj px", False),
}
NUM_WORST_SCENES = 5
NUM_WORST_MOMENTS = 15


def view_command(row: dict, frame: int | None, track: int | None = None) -> str:
    """The command that opens ``row``'s scene and results at ``frame`` in the viewer
    (``track`` selected)."""
    parts = ["python", "app.py", row["scene"], "--out", row["results"]]
    if row.get("config_file"):
        parts += ["--config", row["config_file"]]
    for s in row.get("set_args", []):
        parts += ["--set", s]
    if frame is not None:
        parts += ["--frame", str(frame)]
    if track is not None and track >= 0:
        parts += ["--track", str(track)]
    return shlex.join(parts)


def _mean(values: list) -> float | None:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return sum(v) / len(v) if v else None


def build_report(
    rows: Sequence[dict], *, sweeps: Sequence[str] = (), started_at: float | None = None
) -> dict:
    """The report of ``rows``: one dict per job with ``scene``, ``label``, ``setting``,
    ``status``, ``error``, ``results``, ``summary`` (None if it failed), ``seconds``;
    ``started_at``: when the batch command started (Unix time), for its timeline."""
    rows = [dict(r) for r in rows]
    moments = []
    for r in rows:
        s = r.get("summary") or {}
        worst = s.get("worst") or []
        first = worst[0] if worst else {}
        r["view_command"] = view_command(r, first.get("frame"), first.get("track"))
        for m in worst:
            cmd = view_command(r, m["frame"], m["track"])
            moments.append(dict(m, label=r["label"], command=cmd))
    # mm against mm first (scenes with ground truth), then px where none has it
    moments.sort(key=lambda m: (m["metric"] != "mpjpe_mm", -m["value"]))
    scored = [r for r in rows if (r.get("summary") or {}).get("mpjpe_mm") is not None]
    key = "mpjpe_mm" if scored else "reprojection_mean_px"
    ranked = [r for r in rows if (r.get("summary") or {}).get(key) is not None]
    ranked.sort(key=lambda r: -r["summary"][key])
    settings: dict[tuple, list[dict]] = {}
    for r in rows:
        settings.setdefault(tuple(r.get("setting", ())), []).append(r)
    sweep_table = [
        {
            "setting": list(setting),
            "scenes_ok": sum(r["status"] != "failed" for r in group),
            "scenes_failed": sum(r["status"] == "failed" for r in group),
            **{m: _mean([(r.get("summary") or {}).get(m) for r in group]) for m in METRICS},
        }
        for setting, group in settings.items()
    ]
    return {
        "version": REPORT_VERSION,
        "sweeps": list(sweeps),
        "rows": rows,
        "worst_scenes": {
            "metric": key,
            "labels": [r["label"] for r in ranked[:NUM_WORST_SCENES]],
        },
        "worst_moments": moments[:NUM_WORST_MOMENTS],
        "settings": sweep_table,
        "counts": {
            s: sum(r["status"] == s for r in rows) for s in ("computed", "cached", "failed")
        },
        "timeline": task_timeline(rows, started_at),
    }


# a one-task scene's stages, in the order they run, and their colours in the timeline
TASK_STAGES = {
    "load": ("reading", "#8c8c8c"),
    "frames": ("restoration + association + triangulation", "#4c72b0"),
    "sequence_fit": ("tracking + filters + SMPL fit", "#dd8452"),
    "summary_save": ("figures + saving", "#55a868"),
}


def task_timeline(rows: Sequence[dict], started_at: float | None = None) -> dict | None:
    """Where a batch's time went, from its one-task scenes' rows (``task_seconds`` with
    ``started_at`` / ``ended_at`` / ``pid``; chunked and reused scenes have none): the
    workers (numbered in the order of their first task), each task's label, worker,
    start and end in seconds from the first task's start and its stages' walls, the
    span from the first start to the last end, the share of it the workers were busy,
    and with ``started_at`` (the command's start, Unix time) the start-up before the
    first task (``startup_s``: Ray, the workers' imports). None without such a row."""
    timed = [r for r in rows if (r.get("task_seconds") or {}).get("started_at") is not None]
    if not timed:
        return None
    t0 = min(r["task_seconds"]["started_at"] for r in timed)
    span = max(r["task_seconds"]["ended_at"] for r in timed) - t0
    startup = round(t0 - started_at, 3) if started_at is not None else None
    order = sorted(timed, key=lambda r: r["task_seconds"]["started_at"])
    workers = list(dict.fromkeys(r["task_seconds"]["pid"] for r in order))
    tasks = [
        {
            "label": r["label"],
            "worker": workers.index(r["task_seconds"]["pid"]),
            "start_s": round(r["task_seconds"]["started_at"] - t0, 3),
            "end_s": round(r["task_seconds"]["ended_at"] - t0, 3),
            "stages_s": {k: r["task_seconds"].get(f"{k}_s", 0.0) for k in TASK_STAGES},
        }
        for r in order
    ]
    busy = sum(t["end_s"] - t["start_s"] for t in tasks)
    return {
        "workers": len(workers),
        "span_s": round(span, 3),
        "busy": round(busy / (len(workers) * span), 3) if span > 0 else 1.0,
        "startup_s": startup,
        "tasks": tasks,
    }


def load_report(path: str | os.PathLike) -> dict:
    """A ``batch_report.json`` (or the directory holding one), checked."""
    path = Path(path)
    if path.is_dir():
        path = path / REPORT_JSON
    try:
        report = json.loads(path.read_text())
    except FileNotFoundError:
        raise SceneFormatError(path, None, "not found: run mvviz batch first") from None
    except ValueError as exc:
        raise SceneFormatError(path, None, f"not JSON ({exc})") from None
    if not isinstance(report, dict) or report.get("version") != REPORT_VERSION:
        raise SceneFormatError(path, "version", f"expected {REPORT_VERSION}")
    if not isinstance(report.get("rows"), list):
        raise SceneFormatError(path, "rows", "expected a list of scenes")
    return report


def write_report(report: dict, directory: str | os.PathLike) -> tuple[Path, Path]:
    """Write ``batch_report.json`` and ``batch_report.html`` into ``directory``
    (atomically); returns their paths."""
    d = Path(directory)
    with atomic_write(d / REPORT_JSON, "w") as fh:
        json.dump(report, fh, indent=1)
    with atomic_write(d / REPORT_HTML, "w") as fh:
        fh.write(render_html(report))
    return d / REPORT_JSON, d / REPORT_HTML


# --------------------------------------------------------------------------- html


def _fmt(x, digits: int = 1) -> str:
    if x is None:
        return "–"
    if isinstance(x, int):
        return str(x)
    return f"{x:.{digits}f}" if abs(x) >= 1 or x == 0 else f"{x:.3f}"


def _image(fig) -> str:
    """The figure as an inline SVG image. Vector, so it stays sharp when zoomed, and its
    text is left to the browser's fonts (``svg.fonttype`` none) rather than drawn as
    glyph paths: ~0.15 s less than a PNG for a report's figures, at the end of every
    batch (an ``<img>``, not inline markup, so the figures' element ids cannot clash)."""
    buf = io.StringIO()
    with matplotlib.rc_context({"svg.fonttype": "none"}):
        fig.savefig(buf, format="svg", bbox_inches="tight")
    plt.close(fig)
    data = base64.b64encode(buf.getvalue().encode()).decode()
    return f'<img alt="plot" src="data:image/svg+xml;base64,{data}">'


def _bar_plot(rows: list[dict], metric: str) -> str:
    vals = [(r["label"], r["summary"][metric]) for r in rows if r.get("summary")]
    vals = [(lab, v) for lab, v in vals if v is not None]
    if not vals:
        return ""
    fig, ax = plt.subplots(figsize=(7, 0.3 * len(vals) + 1.0))
    ax.barh([lab for lab, _ in vals], [v for _, v in vals], color="#4c72b0")
    ax.invert_yaxis()
    ax.set_xlabel(METRICS[metric][0])
    ax.set_title(f"{METRICS[metric][0]} per scene")
    return _image(fig)


def _timeline_plot(timeline: dict) -> str:
    """The scene tasks per worker in time, each split into its stages."""
    fig, ax = plt.subplots(figsize=(8, 0.45 * timeline["workers"] + 1.4))
    lead = timeline.get("startup_s") or 0.0  # the command's start at 0, where known
    labels = []  # (task, its label's text): shortened to their bars once the axis is set
    if lead > 0:
        ax.axvspan(0, lead, color="#e8e8e8", zorder=0)
        ax.text(lead / 2, (timeline["workers"] - 1) / 2, f"start-up\n{lead:.1f} s", ha="center",
                va="center", fontsize=8, color="#555")  # fmt: skip
    for t in timeline["tasks"]:
        t = dict(t, start_s=t["start_s"] + lead, end_s=t["end_s"] + lead)
        x = t["start_s"]
        for k, (_, colour) in TASK_STAGES.items():
            w = t["stages_s"].get(k, 0.0)
            ax.barh(t["worker"], w, left=x, height=0.6, color=colour, edgecolor="none")
            x += w
        ax.barh(t["worker"], t["end_s"] - t["start_s"], left=t["start_s"], height=0.6,
                fill=False, edgecolor="#333", linewidth=0.6)  # fmt: skip
        middle = (t["start_s"] + t["end_s"]) / 2
        text = ax.text(middle, t["worker"], t["label"], ha="center", va="center", fontsize=7,
                       color="white")  # fmt: skip
        labels.append((t, text))
    ax.set_yticks(range(timeline["workers"]), [f"worker {i}" for i in range(timeline["workers"])])
    ax.invert_yaxis()
    ax.set_xlabel("seconds from the batch command's start" if lead > 0
                  else "seconds from the first scene task's start")  # fmt: skip
    ax.set_title(
        f"{len(timeline['tasks'])} scene tasks on {timeline['workers']} workers: busy "
        f"{100 * timeline['busy']:.0f} % of {timeline['span_s']:.1f} s"
    )
    renderer = fig.canvas.get_renderer()
    for t, text in labels:
        (x0, _), (x1, _) = ax.transData.transform([(t["start_s"], 0), (t["end_s"], 0)])
        _fit_label(text, 0.9 * (x1 - x0), renderer)
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for _, c in TASK_STAGES.values()]
    ax.legend(handles, [name for name, _ in TASK_STAGES.values()], fontsize=7,
              loc="upper center", bbox_to_anchor=(0.5, -0.35), ncol=2, frameon=False)  # fmt: skip
    return _image(fig)


def _fit_label(text, width_px: float, renderer) -> None:
    """Shorten a bar's label to its longest prefix (with an ellipsis) that fits
    ``width_px``, or remove it where not even three letters fit: a short task's label
    would run over its neighbours' (scene names with a sweep setting are long)."""
    label = text.get_text()

    def fits(n: int) -> bool:
        text.set_text(label if n == len(label) else label[:n] + "\u2026")
        return text.get_window_extent(renderer).width <= width_px

    if fits(len(label)):
        return
    lo, hi = 3, len(label) - 1  # the longest prefix that fits, by bisection
    if lo > hi or not fits(lo):
        text.remove()
        return
    while lo < hi:
        mid = (lo + hi + 1) // 2
        lo, hi = (mid, hi) if fits(mid) else (lo, mid - 1)
    fits(lo)


def _sweep_plots(report: dict) -> list[str]:
    """Per swept field: each metric's mean over scenes against the field's value (one
    line per combination of the other fields)."""
    out = []
    settings = report["settings"]
    for sweep in report["sweeps"]:
        field = sweep.partition("=")[0].strip()
        metrics = [m for m in METRICS if any(s[m] is not None for s in settings)]
        if not metrics:
            continue
        fig, axes = plt.subplots(1, len(metrics), figsize=(3.0 * len(metrics), 2.6))
        axes = [axes] if len(metrics) == 1 else list(axes)
        lines: dict[tuple, list[tuple[float, dict]]] = {}
        for s in settings:
            value = next(a.partition("=")[2] for a in s["setting"] if a.startswith(field + "="))
            others = tuple(a for a in s["setting"] if not a.startswith(field + "="))
            lines.setdefault(others, []).append((float(value), s))
        for ax, m in zip(axes, metrics, strict=True):
            for others, pts in lines.items():
                pts.sort(key=lambda p: p[0])
                ys = [p[1][m] if p[1][m] is not None else float("nan") for p in pts]
                ax.plot([p[0] for p in pts], ys, "o-", label=", ".join(others) or None)
            xs = [p[0] for pts in lines.values() for p in pts]
            if min(xs) > 0 and max(xs) / min(xs) >= 20:  # values over decades
                ax.set_xscale("log")
            ax.set_xlabel(field)
            ax.set_title(METRICS[m][0], fontsize=9)
        if any(lines):
            axes[-1].legend(fontsize=6)
        fig.tight_layout()
        out.append(f"<h3>{html.escape(field)}</h3>{_image(fig)}")
    return out


def _table(header: list[str], body: list[list[str]]) -> str:
    th = "".join(f"<th>{h}</th>" for h in header)
    tr = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in body)
    return f"<table><thead><tr>{th}</tr></thead><tbody>{tr}</tbody></table>"


def _code(cmd: str) -> str:
    return f"<code>{html.escape(cmd)}</code>"


def _scene_rows(rows: list[dict]) -> list[list[str]]:
    """The Scenes table's cells: label, status (and error), metrics, viewer command."""
    esc = html.escape
    out = []
    for r in rows:
        s = r.get("summary") or {}
        status = f'<span class="status">{esc(r["status"])}</span>' + (
            f': <span class="err">{esc(r["error"])}</span>' if r.get("error") else ""
        )
        out.append(
            [esc(r["label"]), status]
            + [_fmt(s.get(m), 3 if m in ("pck160", "pcp") else 1) for m in METRICS]
            + [_code(r["view_command"])]
        )
    return out


def render_html(report: dict) -> str:
    rows = report["rows"]
    esc = html.escape
    scene_rows = _scene_rows(rows)
    cams = sorted(
        {v for r in rows for v in ((r.get("summary") or {}).get("reprojection_px") or {})}
    )
    cam_rows = [
        [esc(r["label"])] + [_fmt((r["summary"]["reprojection_px"] or {}).get(c)) for c in cams]
        for r in rows
        if r.get("summary")
    ]
    moment_rows = [
        [esc(m["label"]), str(m["frame"]), str(m["track"]), esc(m["metric"]), _fmt(m["value"]),
         _code(m["command"])]
        for m in report["worst_moments"]
    ]  # fmt: skip
    setting_rows = [
        [esc(", ".join(s["setting"]) or "(base config)"), str(s["scenes_ok"]),
         str(s["scenes_failed"])]
        + [_fmt(s[m], 3 if m in ("pck160", "pcp") else 1) for m in METRICS]
        for s in report["settings"]
    ]  # fmt: skip
    worst = report["worst_scenes"]
    metric = worst["metric"]
    plot = _bar_plot([r for r in rows if r.get("summary")], metric)
    counts = report["counts"]
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>mvviz batch report</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>mvviz batch report</h1>",
        f"<p>{len(rows)} runs: {counts['computed']} computed, {counts['cached']} reused, "
        f"{counts['failed']} failed.</p>",
        "<h2>Scenes</h2>",
        _table(["scene", "status", *[t for t, _ in METRICS.values()], "open in the viewer"],
               scene_rows),
        f"<h2>Worst scenes (by {esc(METRICS[metric][0])})</h2>",
        "<ol>" + "".join(f"<li>{esc(lab)}</li>" for lab in worst["labels"]) + "</ol>",
        plot,
        "<h2>Worst moments across the dataset</h2>",
        _table(["scene", "frame", "track", "metric", "value", "open at that frame"], moment_rows),
        "<h2>Reprojection error per camera (px)</h2>",
        _table(["scene", *[esc(c) for c in cams]], cam_rows),
    ]  # fmt: skip
    timeline = report.get("timeline")
    if timeline:
        parts += [
            "<h2>Where the time went</h2>",
            f"<p>The scene tasks run as one task each, per worker (scenes split into frame "
            f"chunks and reused ones are not shown): {len(timeline['tasks'])} tasks on "
            f"{timeline['workers']} workers, busy {100 * timeline['busy']:.0f} % of the "
            f"{timeline['span_s']:.1f} s from the first task's start to the last one's "
            f"end"
            + (
                f", after {timeline['startup_s']:.1f} s of start-up (Ray's processes, the "
                f"workers' imports) from the command's start"
                if timeline.get("startup_s")
                else ""
            )
            + ".</p>",
            _timeline_plot(timeline),
        ]
    if report["sweeps"]:
        parts += [
            "<h2>Sweep: the metrics per setting (mean over scenes)</h2>",
            _table(["setting", "ok", "failed", *[t for t, _ in METRICS.values()]], setting_rows),
            "<h2>Metric against parameter</h2>",
            *_sweep_plots(report),
        ]
    parts.append("</body></html>")
    return "\n".join(parts)


_CSS = """
body { font: 14px system-ui, sans-serif; margin: 24px; color: #222; }
table { border-collapse: collapse; margin: 8px 0 20px; }
th, td { border: 1px solid #ccc; padding: 3px 7px; text-align: right; }
th { background: #f0f0f0; }
td { white-space: nowrap; }
td:first-child { white-space: normal; }
td:first-child, th:first-child, td:has(code), td:has(.status) { text-align: left; }
/* a viewer command or an error (long paths) wraps inside its cell, not the page */
td:has(code), td:has(.err) { white-space: normal; overflow-wrap: anywhere; }
td:has(code) { min-width: 22em; }
td:has(.err) { min-width: 12em; }
code { font-size: 11px; background: #f7f7f7; user-select: all; }
img { max-width: 100%; }
"""
