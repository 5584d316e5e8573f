"""The time series under ``plots/``, sent as columns (see :mod:`mvviz.export.rerun`)."""

from __future__ import annotations

import numpy as np
import rerun as rr

from mvviz.export.rerun.layout import AXIS_COLORS, track_color


def _send_series(rec, path: str, frames: np.ndarray, values: np.ndarray, fps: float) -> None:
    ok = np.isfinite(values)
    if not ok.any():
        return
    fr = frames[ok]
    rec.send_columns(
        path,
        indexes=[rr.TimeColumn("frame", sequence=fr), rr.TimeColumn("time", duration=fr / fps)],
        columns=rr.Scalars.columns(scalars=values[ok].astype(np.float64)),
    )


def _log_plots(
    rec,
    scene,
    results,
    frame_ids,
    plot_idx,
    person_by_frame,
    gt_by_frame,
    *,
    branch: str = "",
    filtered: np.ndarray | None = None,
    mahalanobis: np.ndarray | None = None,
    raw: bool = True,
    counts: bool = True,
    styles: bool = True,
) -> None:
    """Joint coordinates per track, Mahalanobis distances and counts over ``frame_ids``,
    as columns.

    ``branch`` suffixes the stage and metric names (see the module docstring);
    ``filtered`` (K, F, J, 3) mm and ``mahalanobis`` (K, F, J) replace the results' own
    (filter B); without ``raw`` / ``counts`` those series are left out. The series'
    line styles are static: a caller sending a scene's frames in pieces logs them with
    the first piece only (``styles``). Only ``frame_ids``' rows of the (K, F, ...) arrays
    are read, so a piece costs memory in its own length, not the scene's.
    """
    fps = scene.fps
    filtered = results.track_filtered if filtered is None else filtered
    mahalanobis = results.track_mahalanobis if mahalanobis is None else mahalanobis
    stages = (("raw", results.track_raw, 1.0),) if raw else ()
    stages += (("filtered", filtered, 2.0),)
    for k in range(results.num_tracks):
        for name, idx in plot_idx.items():
            for stage, arr, width in stages:
                xyz = arr[k][frame_ids][:, idx].mean(1)  # (F, 3) mm
                for a, axis in enumerate("xyz"):
                    path = f"plots/joints/{k}/{name}/{stage}{branch}/{axis}"
                    color = AXIS_COLORS[a] if stage == "filtered" else _dim(AXIS_COLORS[a])
                    if branch:
                        width = 1.0 if stage == "raw" else 1.5
                    if styles:
                        rec.log(
                            path,
                            rr.SeriesLines(
                                colors=[color],
                                widths=[width],
                                names=[f"{k} {name} {stage}{branch} {axis}"],
                            ),
                            static=True,
                        )
                    _send_series(rec, path, frame_ids, xyz[:, a], fps)
        maha = mahalanobis[k][frame_ids]  # (F, J)
        with np.errstate(invalid="ignore"):
            finite = np.isfinite(maha)
            mean = np.where(
                finite.any(1), np.nansum(np.where(finite, maha, 0), 1) / finite.sum(1), np.nan
            )
        path = f"plots/metrics/mahalanobis{branch}/{k}"
        if styles:
            rec.log(
                path,
                rr.SeriesLines(colors=[track_color(k)], names=[f"track {k}{branch}"]),
                static=True,
            )
        _send_series(rec, path, frame_ids, mean, fps)
    if not counts:
        return
    series = {
        "people": np.array([len(person_by_frame.get(int(f), ())) for f in frame_ids], float),
        "tracks": _tracks_per_frame(filtered, frame_ids),
    }
    if scene.gt is not None and not branch:
        series["gt_people"] = np.array([len(gt_by_frame.get(int(f), ())) for f in frame_ids], float)
    for name, values in series.items():
        path = f"plots/metrics/{name}{branch}"
        if styles:
            rec.log(path, rr.SeriesLines(names=[f"{name}{branch}"]), static=True)
        _send_series(rec, path, frame_ids, values, fps)


def _tracks_per_frame(filtered: np.ndarray, frame_ids: np.ndarray) -> np.ndarray:
    """(F',) float: tracks with a fully finite joint at each of ``frame_ids``; read
    track by track, never as a (K, F', J, 3) copy."""
    n = np.zeros(len(frame_ids))
    for k in range(len(filtered)):
        n += np.isfinite(filtered[k][frame_ids]).all(-1).any(-1)
    return n


def _dim(color: tuple[int, int, int]) -> tuple[int, int, int]:
    return tuple(int(0.55 * c + 0.45 * 128) for c in color)
