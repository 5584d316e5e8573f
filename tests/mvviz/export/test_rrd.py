"""mvviz.export.rrd: a tiny synthetic scene exported to .rrd and read back."""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from rerun.chunk import RrdReader

from mvviz.cli import main
from mvviz.export import rrd as rerun_export
from mvviz.export.rrd import (
    DEFAULT_PLOT_JOINTS,
    ClassLayout,
    decimate_mesh,
    export_rrd,
    read_rrd_summary,
    resolve_plot_joint,
    select_frames,
)
from pipeline.body.model import load_body_model
from pipeline.data.joint_sets import COCO17
from tests.mvviz.conftest import synth_campus_scene

REPO = Path(__file__).resolve().parents[3]
CAMPUS = REPO / "sample_data" / "rigs" / "campus_voxelpose.json"
NUM_FRAMES = 10


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    """(scene, results, model): 2 people, 10 frames on the campus rig, with videos."""
    return synth_campus_scene(tmp_path_factory.mktemp("rrd") / "scene", NUM_FRAMES)


@pytest.fixture(scope="session")
def exported(tiny, tmp_path_factory):
    scene, results, model = tiny
    path = tmp_path_factory.mktemp("out") / "tiny.rrd"
    export_rrd(scene, results, model, path, image_width=240, progress=False)
    return path, read_rrd_summary(path)


def rerun_cli() -> str | None:
    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.is_file() else shutil.which("rerun")


def one(rows: list) -> np.ndarray:
    """The value of a component logged once, with one instance."""
    ((_, batch),) = rows
    (value,) = batch
    return np.asarray(value, float)


def rows_of(path: Path, entity: str, component: str) -> list:
    """``(frame, batch)`` of every row of ``component`` at ``entity`` (frame None if static);
    a batch is the list of the row's instances."""
    out = []
    for chunk in RrdReader(str(path)).stream():
        if str(chunk.entity_path) == entity:
            batch = chunk.to_record_batch()
            if component in batch.schema.names:
                frames = (
                    batch.column("frame").to_pylist()
                    if "frame" in batch.schema.names
                    else [None] * batch.num_rows
                )
                out += list(zip(frames, batch.column(component).to_pylist(), strict=True))
    return out


# --------------------------------------------------------------------------- the file


@pytest.mark.slow
def test_export_writes_a_file_that_rerun_verifies(exported):
    path, _ = exported
    assert path.stat().st_size > 10_000
    exe = rerun_cli()
    if exe is None:
        pytest.skip("the rerun CLI (shipped in the rerun-sdk wheel) is not on this machine")
    proc = subprocess.run(
        [exe, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "verified without error" in proc.stdout + proc.stderr


def test_entities_cover_cameras_skeletons_meshes_and_plots(tiny, exported):
    scene, results, _ = tiny
    _, summary = exported
    comp = summary.components
    for cam in scene.rig.names:
        base = f"/world/cameras/{cam}"
        assert {"Pinhole:image_from_camera", "Transform3D:translation"} <= comp[base]
        assert base in summary.static_entities
        assert "EncodedImage:blob" in comp[f"{base}/image"]
        assert summary.rows[f"{base}/image"] == NUM_FRAMES
        assert "Points2D:keypoint_ids" in comp[f"{base}/detections"]
    assert results.num_tracks >= 2
    for k in range(results.num_tracks):
        for stage in ("raw", "filtered"):
            assert "Points3D:keypoint_ids" in comp[f"/world/skeletons/{stage}/{k}"]
            for joint in DEFAULT_PLOT_JOINTS:
                for axis in "xyz":
                    path = f"/plots/joints/{k}/{joint}/{stage}/{axis}"
                    assert "Scalars:scalars" in comp[path], path
        assert "Scalars:scalars" in comp[f"/plots/metrics/mahalanobis/{k}"]
        assert "LineStrips3D:strips" in comp[f"/world/rays/{k}"]
    for p in np.unique(scene.gt.person_id):
        assert {"Mesh3D:triangle_indices", "Mesh3D:vertex_positions"} <= comp[
            f"/world/meshes/gt/{p}"
        ]
        assert "Points3D:positions" in comp[f"/world/skeletons/gt/{p}"]
    for name in ("people", "tracks", "gt_people"):
        assert summary.rows[f"/plots/metrics/{name}"] >= NUM_FRAMES
    assert {"AnnotationContext:context", "ViewCoordinates:xyz"} <= comp["/world"]


def test_blueprint_has_a_3d_view_one_2d_view_per_camera_and_two_plots(tiny, exported):
    scene, _, _ = tiny
    path, _ = exported
    reader = RrdReader(str(path))
    (blueprint,) = reader.blueprints()
    views = {
        str(c.entity_path)
        for c in reader.stream(store=blueprint)
        if str(c.entity_path).startswith("/view/") and str(c.entity_path).count("/") == 2
    }
    assert len(views) == 1 + len(scene.rig) + 2


def test_frame_timeline_has_every_scene_frame(tiny, exported):
    scene, _, _ = tiny
    _, summary = exported
    assert scene.num_frames == NUM_FRAMES
    np.testing.assert_array_equal(summary.frames, np.arange(scene.num_frames))


def test_logged_numbers_match_the_scene_and_results(tiny, exported):
    scene, results, model = tiny
    path, _ = exported
    cam = scene.rig[1]
    # Camera pose in metres; pinhole scaled to the 240 px wide image.
    t = one(rows_of(path, f"/world/cameras/{cam.name}", "Transform3D:translation"))
    np.testing.assert_allclose(t, cam.center / 1000, atol=1e-5)
    R = one(rows_of(path, f"/world/cameras/{cam.name}", "Transform3D:mat3x3"))
    np.testing.assert_allclose(np.reshape(R, (3, 3), order="F"), cam.R.T, atol=1e-6)
    K = one(rows_of(path, f"/world/cameras/{cam.name}", "Pinhole:image_from_camera"))
    K = np.reshape(K, (3, 3), order="F")
    s = 240 / cam.width
    np.testing.assert_allclose(K[0, 0], s * cam.K[0, 0], rtol=1e-6)
    np.testing.assert_allclose(K[:2, 2], s * (cam.K[:2, 2] + 0.5), rtol=1e-6)
    res = one(rows_of(path, f"/world/cameras/{cam.name}", "Pinhole:resolution"))
    np.testing.assert_array_equal(res, [240, round(cam.height * s)])
    # Images decode to that size.
    _, (blob,) = rows_of(path, f"/world/cameras/{cam.name}/image", "EncodedImage:blob")[3]
    img = cv2.imdecode(np.frombuffer(bytes(blob), np.uint8), cv2.IMREAD_COLOR)
    assert img.shape[:2] == (int(res[1]), int(res[0]))
    # The filtered skeleton of track 0 at frame 4 in metres, joints kept by keypoint id.
    pos = dict(rows_of(path, "/world/skeletons/filtered/0", "Points3D:positions"))[4]
    ids = dict(rows_of(path, "/world/skeletons/filtered/0", "Points3D:keypoint_ids"))[4]
    want = results.track_filtered[0, 4]
    np.testing.assert_array_equal(ids, np.flatnonzero(np.isfinite(want).all(1)))
    np.testing.assert_allclose(pos, want[ids] / 1000, atol=1e-6)
    # 2D detections: s * (pixel + 0.5) of the rows of that view and frame with confidence.
    rows = np.flatnonzero((scene.detections.frame == 4) & (scene.detections.view == 1))
    kp = results.det_joints2d[rows]
    kp = kp[kp[..., 2] > 0]
    pts = dict(rows_of(path, f"/world/cameras/{cam.name}/detections", "Points2D:positions"))[4]
    np.testing.assert_allclose(
        np.sort(np.asarray(pts), 0), np.sort(s * (kp[:, :2] + 0.5), 0), atol=1e-3
    )
    # Pelvis plot of track 0 (COCO-17: mean of the hips), mm.
    hips = [COCO17.index["left_hip"], COCO17.index["right_hip"]]
    z = dict(rows_of(path, "/plots/joints/0/pelvis/raw/z", "Scalars:scalars"))
    assert len(z) >= NUM_FRAMES - 2
    for f, (v,) in z.items():
        np.testing.assert_allclose(v, results.track_raw[0, f, hips, 2].mean(), rtol=1e-9)
    # GT mesh: the body model's vertices (decimated at 25 mm) plus transl, metres.
    mesh = np.asarray(dict(rows_of(path, "/world/meshes/gt/0", "Mesh3D:vertex_positions"))[2])
    row = np.flatnonzero((scene.gt.frame == 2) & (scene.gt.person_id == 0))[0]
    keep, faces = decimate_mesh(
        model.v_template.numpy(), model.faces.numpy(), model.weights.numpy(), 0.025
    )
    with torch.no_grad():
        verts = model(
            torch.as_tensor(scene.gt.smpl_pose[row : row + 1], dtype=torch.float32),
            torch.as_tensor(scene.gt.smpl_betas[row : row + 1], dtype=torch.float32),
        ).vertices.numpy()[0]
    np.testing.assert_allclose(mesh, verts[keep] + scene.gt.transl[row] / 1000, atol=1e-5)
    assert np.linalg.norm(mesh.mean(0) - scene.gt.joints3d[row, 0] / 1000) < 0.3
    ((_, logged_faces),) = rows_of(path, "/world/meshes/gt/0", "Mesh3D:triangle_indices")
    np.testing.assert_array_equal(logged_faces, faces)
    assert len(mesh) < model.num_vertices / 3


def body_stages(results) -> list[str]:
    """The fits the results hold (step I, and with the VAE prior when it is shipped)."""
    stages = [s for s in ("smpl", "smpl_vae") if getattr(results, s) is not None]
    assert "smpl" in stages
    return stages


@pytest.mark.slow
def test_fitted_bodies_are_decimated_meshes_per_track_and_frame(tiny, exported):
    """world/bodies/<stage>/<track>: static faces in the track colour, one decimated mesh
    (the fit's vertices at the kept indices) per frame the track is fitted, empty where not."""
    scene, results, _ = tiny
    path, summary = exported
    for stage in body_stages(results):
        fit = getattr(results, stage)
        model = fit.model
        keep, faces = decimate_mesh(
            model.v_template.numpy(), model.faces.numpy(), model.weights.numpy(), 0.025
        )
        for k in range(results.num_tracks):
            ent = f"/world/bodies/{stage}/{k}"
            assert ent in summary.static_entities, ent
            ((_, logged_faces),) = rows_of(path, ent, "Mesh3D:triangle_indices")
            np.testing.assert_array_equal(logged_faces, faces)
            (color,) = one(rows_of(path, ent, "Mesh3D:albedo_factor")).reshape(1)
            want_color = rerun_export.track_color(k, raw=stage == "smpl")
            assert int(color) == int.from_bytes(bytes([*want_color, 255]), "big")
            meshes = dict(rows_of(path, ent, "Mesh3D:vertex_positions"))
            fitted = {f for f in range(NUM_FRAMES) if fit.present[k, f]}
            assert fitted, (stage, k)
            assert {f for f, v in meshes.items() if len(v)} == fitted
            assert all(len(v) == len(keep) for f, v in meshes.items() if f in fitted)
            f = min(fitted)
            np.testing.assert_allclose(
                np.asarray(meshes[f]), fit.vertices(k, f)[keep] / 1000, atol=1e-5
            )


@pytest.mark.slow
def test_full_body_meshes_without_decimation(tiny, tmp_path):
    scene, results, model = tiny
    path = tmp_path / "full.rrd"
    export_rrd(scene, results, model, path, frames=range(3, 5), images=False, meshes=False,
               mesh_cell_mm=None, progress=False)  # fmt: skip
    summary = read_rrd_summary(path)
    assert not any(e.startswith("/world/meshes") for e in summary.rows)
    for stage in body_stages(results):
        fit = getattr(results, stage)
        k = int(np.flatnonzero(fit.present[:, 3])[0])
        meshes = dict(rows_of(path, f"/world/bodies/{stage}/{k}", "Mesh3D:vertex_positions"))
        assert len(meshes[3]) == fit.model.num_vertices
        np.testing.assert_allclose(np.asarray(meshes[3]), fit.vertices(k, 3) / 1000, atol=1e-5)
    exe = rerun_cli()
    if exe is not None:
        proc = subprocess.run([exe, "rrd", "verify", str(path)], capture_output=True, text=True,
                              timeout=120)  # fmt: skip
        assert proc.returncode == 0, proc.stdout + proc.stderr
    path2 = tmp_path / "none.rrd"
    export_rrd(scene, results, model, path2, frames=range(3, 5), images=False, bodies=False,
               progress=False)  # fmt: skip
    assert not any(e.startswith("/world/bodies") for e in read_rrd_summary(path2).rows)


def test_rays_end_on_the_triangulated_joints(tiny, exported):
    """Each ray starts at a camera centre and ends within a few cm of a raw joint."""
    scene, results, _ = tiny
    path, _ = exported
    strips = dict(rows_of(path, "/world/rays/0", "LineStrips3D:strips"))[5]
    strips = np.asarray(strips, float)  # (n, 2, 3) metres
    centres = scene.rig.centers / 1000
    d_start = np.linalg.norm(strips[:, None, 0] - centres[None], axis=-1).min(1)
    assert d_start.max() < 1e-4
    q = np.flatnonzero((results.person_frame == 5) & (results.person_track == 0))[0]
    joints = results.person_joints[q] / 1000
    d_end = np.linalg.norm(strips[:, None, 1] - joints[None], axis=-1).min(1)
    assert np.median(d_end) < 0.02
    assert len(strips) == results.person_used[q].sum()


def test_frame_subset_without_images(tiny, tmp_path):
    scene, results, model = tiny
    path = tmp_path / "part.rrd"
    export_rrd(
        scene, results, model, path, frames=range(2, 5), images=False, meshes=False, progress=False
    )
    summary = read_rrd_summary(path)
    np.testing.assert_array_equal(summary.frames, [2, 3, 4])
    assert not any(e.endswith("/image") for e in summary.rows)
    assert not any(e.startswith("/world/meshes") for e in summary.rows)
    cam = scene.rig[0]
    res = one(rows_of(path, f"/world/cameras/{cam.name}", "Pinhole:resolution"))
    np.testing.assert_array_equal(res, [cam.width, cam.height])


# --------------------------------------------------------------------------- failures


def test_unwritable_path_raises_and_writes_nothing(tiny, tmp_path):
    scene, results, model = tiny
    (tmp_path / "a_file").write_text("not a directory")
    target = tmp_path / "a_file" / "run.rrd"
    with pytest.raises(OSError):
        export_rrd(scene, results, model, target, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]
    # Missing parent directories are created, and the file gets the usual mode.
    target = tmp_path / "new" / "dir" / "run.rrd"
    export_rrd(scene, results, model, target, frames=[0], images=False, progress=False)
    assert target.stat().st_mode & 0o777 == 0o666 & ~_umask()
    assert [p.name for p in target.parent.iterdir()] == ["run.rrd"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_failure_midway_leaves_no_partial_file(tiny, tmp_path, monkeypatch):
    scene, results, model = tiny
    calls = {"n": 0}
    real = rerun_export.encode_jpeg

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > 7:
            raise RuntimeError("disk on fire")
        return real(*args, **kwargs)

    monkeypatch.setattr(rerun_export, "encode_jpeg", flaky)
    target = tmp_path / "run.rrd"
    threads = torch.get_num_threads()
    with pytest.raises(RuntimeError, match="disk on fire"):
        export_rrd(scene, results, model, target, progress=False)
    assert list(tmp_path.iterdir()) == []
    assert torch.get_num_threads() == threads  # the export pins torch to 1 thread meanwhile
    # An existing recording survives a failed re-export untouched.
    target.write_bytes(b"old recording")
    calls["n"] = 0
    with pytest.raises(RuntimeError):
        export_rrd(scene, results, model, target, progress=False)
    assert target.read_bytes() == b"old recording"
    assert list(tmp_path.iterdir()) == [target]


def test_results_of_another_scene_are_refused(tiny, tmp_path):
    scene, results, model = tiny
    other = dataclasses.replace(results, num_views=results.num_views + 1)
    with pytest.raises(ValueError, match="do not match"):
        export_rrd(scene, other, model, tmp_path / "x.rrd", progress=False)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- helpers


def test_decimate_mesh_keeps_a_subset_and_valid_faces():
    model = load_body_model()
    rest = model.v_template.numpy()
    faces = model.faces.numpy()
    weights = model.weights.numpy()
    keep, f = decimate_mesh(rest, faces, weights, 1e-6)
    np.testing.assert_array_equal(np.sort(keep), np.arange(len(rest)))
    assert len(f) == len(np.unique(np.sort(faces, 1), axis=0))
    keep, f = decimate_mesh(rest, faces, weights, 0.025)
    assert len(np.unique(keep)) == len(keep) and len(keep) < len(rest) / 3
    assert f.min() >= 0 and f.max() < len(keep)
    assert (f[:, 0] != f[:, 1]).all() and (f[:, 1] != f[:, 2]).all() and (f[:, 0] != f[:, 2]).all()
    # Clusters never mix vertices of different dominant joints.
    group_joint = weights.argmax(1)[keep]
    assert len(np.unique(group_joint)) == len(np.unique(weights.argmax(1)))


def test_class_layout_ids_are_disjoint_and_dense():
    layout = ClassLayout(num_tracks=3, gt_people=(4, 9), num_unassigned=2, num_untracked=1)
    ids = (
        [layout.filtered(k) for k in range(3)]
        + [layout.raw(k) for k in range(3)]
        + [layout.gt(p) for p in (4, 9)]
        + [layout.unassigned(i) for i in range(2)]
        + [layout.untracked(0)]
    )
    assert sorted(ids) == list(range(layout.num_classes)) == list(range(11))


def test_select_frames_and_plot_joints():
    np.testing.assert_array_equal(select_frames(None, 4), [0, 1, 2, 3])
    np.testing.assert_array_equal(select_frames(slice(2, None), 4), [2, 3])
    np.testing.assert_array_equal(select_frames(range(3, 10), 5), [3, 4])
    np.testing.assert_array_equal(select_frames([3, 1, 3], 5), [1, 3])
    with pytest.raises(ValueError, match="outside"):
        select_frames([7], 5)
    np.testing.assert_array_equal(
        resolve_plot_joint(COCO17, "pelvis"), [COCO17.index["left_hip"], COCO17.index["right_hip"]]
    )
    with pytest.raises(ValueError, match="not in joint set coco17"):
        resolve_plot_joint(COCO17, "tail")


def test_cli_export_rrd(tiny, tmp_path, capsys):
    scene, _, _ = tiny
    out = tmp_path / "cli.rrd"
    code = main(["export-rrd", str(scene.root), "-o", str(out), "--frames", "1:4", "--no-images"])
    assert code == 0
    text = capsys.readouterr().out
    assert "reused cached results" in text and "MB" in text and "world/skeletons" in text
    np.testing.assert_array_equal(read_rrd_summary(out).frames, [1, 2, 3])
    assert main(["export-rrd", str(scene.root), "-o", str(out), "--plot-joints", "tail"]) == 2


class _RecordingSource:
    """A frame source that answers every frame with a grey picture and records which."""

    def __init__(self, camera: str) -> None:
        self.camera, self.asked = camera, []

    def read(self, frame: int):
        self.asked.append(frame)
        return np.full((48, 64, 3), 128, np.uint8) if frame >= 0 else None

    def close(self) -> None:
        pass


def test_a_retimed_camera_logs_the_picture_its_rows_were_recorded_in(tiny, tmp_path, monkeypatch):
    """sync.offsets: the camera lagging by d shows frame f + round(d) at f (as the viewer's
    camera panel does, mvviz.scene.images.video_frame); the others stay on f."""
    from pipeline.config import SyncParams

    scene, results, model = tiny
    late, early = scene.rig.names[0], scene.rig.names[1]
    config = dataclasses.replace(
        results.config, sync=SyncParams(offsets=((late, 1.6), (early, -2.4)))
    )
    results = dataclasses.replace(results, config=config)
    sources = {name: _RecordingSource(name) for name in scene.rig.names}
    monkeypatch.setattr(rerun_export, "scene_frame_sources", lambda _scene: sources)
    export_rrd(
        scene, results, model, tmp_path / "r.rrd", frames=range(3, 6), meshes=False,
        bodies=False, image_width=64, progress=False,
    )  # fmt: skip
    assert sources[late].asked == [5, 6, 7]  # round(1.6) = 2
    assert sources[early].asked == [1, 2, 3]  # round(-2.4) = -2
    for other in scene.rig.names[2:]:
        assert sources[other].asked == [3, 4, 5]


def test_log_scene_reads_a_retimed_cameras_picture_at_its_offset(tiny):
    import rerun as rr

    from mvviz.export.rerun import log_scene
    from pipeline.config import SyncParams

    scene, results, model = tiny
    late = scene.rig.names[2]
    config = dataclasses.replace(results.config, sync=SyncParams(offsets=((late, 3.0),)))
    results = dataclasses.replace(results, config=config)
    sources = {name: _RecordingSource(name) for name in scene.rig.names}
    rec = rr.RecordingStream("mvviz-test")
    rec.memory_recording()
    log_scene(
        scene, results, recording=rec, body_model=model, frames=range(0, 2), meshes=False,
        bodies=False, images={n: s.read for n, s in sources.items()}, image_width=64,
    )  # fmt: skip
    assert sources[late].asked == [3, 4]
    assert sources[scene.rig.names[0]].asked == [0, 1]


def mesh_rows(path: Path) -> dict[str, dict[int, np.ndarray]]:
    """entity -> frame -> (V, 3) logged vertex positions, for every mesh entity."""
    out: dict[str, dict[int, np.ndarray]] = {}
    for chunk in RrdReader(str(path)).stream():
        ent = str(chunk.entity_path)
        batch = chunk.to_record_batch()
        if "Mesh3D:vertex_positions" in batch.schema.names and "frame" in batch.schema.names:
            rows = out.setdefault(ent, {})
            frames = batch.column("frame").to_pylist()
            for f, v in zip(
                frames, batch.column("Mesh3D:vertex_positions").to_pylist(), strict=True
            ):
                assert f not in rows, (ent, f)  # every frame once, whatever the chunks
                rows[f] = np.asarray(v, np.float32).reshape(-1, 3)
    return out


@pytest.mark.slow
def test_meshes_sent_in_chunks_are_the_meshes_sent_at_once(tiny, tmp_path):
    """GT meshes and fitted bodies go out 3 frames at a time (a long scene's memory stays
    one chunk's): the same vertices per entity and frame as in one piece, with a person
    who starts late and one who pauses (empty meshes there, from the first frame on)."""
    scene, results, model = tiny
    gt = scene.gt
    # GT person 0 absent at frames 4-5, GT person 1 only from frame 5 on
    keep = ~(
        ((gt.person_id == 0) & np.isin(gt.frame, [4, 5])) | ((gt.person_id == 1) & (gt.frame < 5))
    )
    gt2 = dataclasses.replace(gt, **{k: v[keep] for k, v in gt.arrays().items()})
    scene2 = dataclasses.replace(scene, gt=gt2)
    fits = {}
    for stage in body_stages(results):
        fit = getattr(results, stage)
        transl = fit.transl.copy()
        transl[0, 3:7] = np.nan  # track 0 pauses over a chunk boundary
        transl[1, :4] = np.nan  # track 1 starts in the second chunk
        fits[stage] = dataclasses.replace(fit, transl=transl)
    results2 = dataclasses.replace(results, **fits)
    paths = {}
    for chunk in (3, 0):
        paths[chunk] = tmp_path / f"chunk{chunk}.rrd"
        export_rrd(scene2, results2, model, paths[chunk], images=False,
                   mesh_chunk_frames=chunk, progress=False)  # fmt: skip
    chunked, whole = mesh_rows(paths[3]), mesh_rows(paths[0])
    assert set(chunked) == set(whole) and any("/bodies/" in e for e in whole)
    for ent, rows in whole.items():
        assert set(chunked[ent]) == set(rows), ent
        for f, v in rows.items():
            # skinned in other batches: float32 rounding, ~0.2 micrometres
            np.testing.assert_allclose(chunked[ent][f], v, atol=1e-6, err_msg=f"{ent} frame {f}")
    # the pauses are empty meshes from the first frame on; nothing before it
    assert min(whole["/world/meshes/gt/1"]) == 5
    assert all(len(whole["/world/meshes/gt/0"][f]) == 0 for f in (4, 5))
    for stage in fits:
        assert min(whole[f"/world/bodies/{stage}/1"]) == 4
        track0 = whole[f"/world/bodies/{stage}/0"]
        assert [f for f in range(3, 7) if len(track0[f])] == []
        assert all(len(track0[f]) > 0 for f in (0, 1, 2, 7, 8, 9))


@pytest.mark.slow
def test_chunks_follow_the_exports_flushes_not_its_speed(tiny, tmp_path, monkeypatch):
    """Rows go into the file's chunks when the export flushes (every ``mesh_chunk_frames``
    frames), however slowly it runs: on rerun's 200 ms clock a slow export wrote a chunk
    per frame, and rerun keeps a little of every chunk until the recording closes."""
    scene, results, model = tiny
    from mvviz.export.rerun.logger import SceneLogger

    log_frame = SceneLogger.log_frame

    def slow_log_frame(self, *args, **kwargs):
        time.sleep(0.25)  # slower than rerun's clock
        return log_frame(self, *args, **kwargs)

    monkeypatch.setattr(SceneLogger, "log_frame", slow_log_frame)
    path = tmp_path / "slow.rrd"
    export_rrd(
        scene, results, model, path, images=False, meshes=False, bodies=False,
        mesh_chunk_frames=3, progress=False,
    )  # fmt: skip
    spans = [
        np.unique(chunk.to_record_batch().column("frame").to_numpy()).tolist()
        for chunk in RrdReader(str(path)).stream()
        if str(chunk.entity_path) == "/world/skeletons/gt/0" and not chunk.is_static
    ]
    assert sorted(spans) == [[0, 1, 2], [3, 4, 5], [6, 7, 8], [9]], spans


def plot_rows(path: Path) -> tuple[dict[str, dict[int, float]], dict[str, int], dict[str, int]]:
    """For every ``/plots`` entity: frame -> value, its number of time-indexed chunks and
    its number of static rows (line styles)."""
    values: dict[str, dict[int, float]] = {}
    chunks: dict[str, int] = {}
    styles: dict[str, int] = {}
    for chunk in RrdReader(str(path)).stream():
        ent = str(chunk.entity_path)
        if not ent.startswith("/plots/"):
            continue
        batch = chunk.to_record_batch()
        if chunk.is_static:
            styles[ent] = styles.get(ent, 0) + batch.num_rows
            continue
        chunks[ent] = chunks.get(ent, 0) + 1
        rows = values.setdefault(ent, {})
        for f, (v,) in zip(
            batch.column("frame").to_pylist(),
            batch.column("Scalars:scalars").to_pylist(),
            strict=True,
        ):
            assert f not in rows, (ent, f)  # every frame once, whatever the pieces
            rows[f] = v
    return values, chunks, styles


def test_plots_sent_in_pieces_are_the_plots_sent_at_once(tiny, tmp_path):
    """The time series go out 4 frames at a time (a long scene's plots wait in rerun's
    queue one piece at a time): the same value per series and frame as in one piece,
    each series cut in one chunk per piece, its line style logged once."""
    import rerun as rr

    from mvviz.export.rerun.logger import SceneLogger

    scene, results, model = tiny
    paths = {}
    for piece in (4, 0):
        paths[piece] = tmp_path / f"plots{piece}.rrd"
        rec = rr.RecordingStream("plots", batcher_config=rerun_export.export_batcher())
        rec.save(paths[piece])
        logger = SceneLogger(scene, results, rec, images=False, meshes=False, bodies=False)
        logger.send_plots(np.arange(NUM_FRAMES), chunk_frames=piece)
        rec.flush()
        rec.disconnect()
    (pieces, piece_chunks, piece_styles), (whole, whole_chunks, whole_styles) = (
        plot_rows(paths[4]), plot_rows(paths[0])
    )  # fmt: skip
    assert set(whole) == set(pieces) and len(whole) > 10
    assert any("/joints/" in e for e in whole) and "/plots/metrics/tracks" in whole
    for ent, rows in whole.items():
        assert pieces[ent] == rows, ent
    assert piece_styles == whole_styles and set(whole_styles.values()) == {1}
    # a series with a value in every piece (0-3, 4-7, 8-9) is cut in 3 chunks, not 1
    assert whole_chunks["/plots/metrics/tracks"] == 1
    assert piece_chunks["/plots/metrics/tracks"] == 3
    counts = np.isfinite(results.track_filtered).all(-1).any(-1).sum(0)
    assert [whole["/plots/metrics/tracks"][f] for f in range(NUM_FRAMES)] == counts.tolist()


@pytest.mark.slow
def test_drains_hand_back_the_pages_of_mapped_results(tiny, tmp_path, monkeypatch):
    """Results opened from a directory are memory-mapped; every drain (each mesh chunk,
    each plot piece, every ``mesh_chunk_frames`` frames) hands the pages read so far back
    for every file map under the scene and its results, and the file is the same as one
    exported from the results in memory."""
    from mvviz.export.rerun import logger as logger_module
    from pipeline.core.npy_stream import is_mapped
    from pipeline.results.store import load_results, save_results

    scene, results, model = tiny
    save_results(results, tmp_path / "results")
    mapped = load_results(tmp_path / "results", model=model)
    released: list[int] = []
    release = logger_module.release_pages

    def counting_release(arr):
        assert is_mapped(arr)
        released.append(id(arr))
        return release(arr)

    monkeypatch.setattr(logger_module, "release_pages", counting_release)
    export_rrd(scene, mapped, model, tmp_path / "mapped.rrd", images=False,
               mesh_chunk_frames=4, progress=False)  # fmt: skip
    maps = len(set(released))
    assert maps >= 10  # one per .npy file the results directory holds
    # frames 0-3 and 4-7 (2 drains), GT meshes and bodies per chunk, plots: one piece
    assert len(released) % maps == 0 and len(released) // maps >= 5
    released.clear()
    export_rrd(scene, results, model, tmp_path / "memory.rrd", images=False,
               mesh_chunk_frames=4, progress=False)  # fmt: skip
    assert released == []  # nothing mapped in memory
    assert mesh_rows(tmp_path / "mapped.rrd").keys() == mesh_rows(tmp_path / "memory.rrd").keys()
    assert plot_rows(tmp_path / "mapped.rrd")[0] == plot_rows(tmp_path / "memory.rrd")[0]
