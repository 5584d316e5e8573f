"""Occlusion at keypoint pixels only (pipeline.synth.occlusion) and the proxy body
(pipeline.synth.proxy): exact against full renders, close with the decimated mesh."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from pipeline.body.model import load_body_model
from pipeline.synth.motion import plan_people
from pipeline.synth.occlusion import point_occlusion
from pipeline.synth.proxy import pose_proxy, proxy_bodies, proxy_for
from pipeline.synth.render import MeshInstance, occluded_by_other, render_meshes, visible_mask
from pipeline.synth.rigs import dome_capture_radius, dome_rig
from pipeline.synth.scene_gen import bodies_from_motion, visible_floor_area


@pytest.fixture(scope="module")
def crowd():
    """6 people on a 6-camera dome, one frame: full-mesh vertices and the truth."""
    model = load_body_model()
    rig = dome_rig(6)
    area = visible_floor_area(rig, within_mm=dome_capture_radius())
    people = bodies_from_motion(plan_people(np.random.default_rng(1), area, 6, 1, 25.0), model)
    with torch.no_grad():
        out = model(
            torch.as_tensor(people.pose[:, 0], dtype=torch.float32),
            torch.as_tensor(people.betas, dtype=torch.float32),
        )
    verts = out.vertices.numpy() * 1000 + people.transl[:, 0, None]
    return model, rig, people, verts


@pytest.mark.slow
def test_keypoint_depths_equal_a_full_render(crowd):
    model, rig, people, verts = crowd
    faces = model.faces.numpy()
    pts = people.keypoints[:, 0].reshape(-1, 3)
    ids = np.repeat(np.arange(len(verts)), people.keypoints.shape[2])
    occ = point_occlusion(list(rig), verts, faces, pts)
    meshes = [MeshInstance(vertices=v, faces=faces) for v in verts]
    hidden = 0
    for k, cam in enumerate(rig):
        r = render_meshes(cam, meshes, cull_back_faces=False)
        vis = visible_mask(r, cam, pts, ids, tolerance_mm=120.0)
        np.testing.assert_array_equal(occ.visible(ids, tolerance_mm=120.0)[k], vis)
        other = occluded_by_other(r, cam, pts, ids)
        np.testing.assert_array_equal(occ.hidden_by_other(ids)[k], other)
        hidden += int(other.sum())
    assert hidden > 0  # the crowd does hide someone: the comparison has teeth


def test_proxy_is_the_model_at_its_vertices_and_much_smaller(crowd):
    model, _, people, verts = crowd
    proxy = proxy_for(model)
    assert len(proxy.faces) < len(model.faces) / 8
    posed = pose_proxy(proxy_bodies(model, proxy, people.betas), people.pose[:, 0]) * 1000
    posed += people.transl[:, 0, None]
    np.testing.assert_allclose(posed, verts[:, proxy.vertex_ids], atol=1e-3)


@pytest.mark.slow
def test_proxy_occlusion_agrees_with_the_full_mesh(crowd):
    model, rig, people, verts = crowd
    proxy = proxy_for(model)
    posed = pose_proxy(proxy_bodies(model, proxy, people.betas), people.pose[:, 0]) * 1000
    posed += people.transl[:, 0, None]
    pts = people.keypoints[:, 0].reshape(-1, 3)
    ids = np.repeat(np.arange(len(verts)), people.keypoints.shape[2])
    full = point_occlusion(list(rig), verts, model.faces.numpy(), pts)
    fast = point_occlusion(list(rig), posed, proxy.faces, pts, cull_back_faces=True)
    a, b = full.visible(ids, tolerance_mm=120.0), fast.visible(ids, tolerance_mm=120.0)
    assert (a != b).mean() < 0.04
    assert abs(a.mean() - b.mean()) < 0.03
    assert abs(full.hidden_by_other(ids).mean() - fast.hidden_by_other(ids).mean()) < 0.03


@pytest.mark.parametrize("distorted", [False, True])
def test_the_cell_prefilter_changes_no_answer(crowd, distorted):
    """The integer pre-filter only drops triangles that cannot cover a query: the same
    depths and owners as the float work on every triangle, with and without distortion
    (the undistorted branch of the projection skips the polynomial)."""
    model, rig, people, _ = crowd
    cams = list(rig)
    if distorted:
        cams = [dataclasses.replace(c, dist=np.array([-0.2, 0.05, 1e-3, -1e-3, 0.0])) for c in cams]
    proxy = proxy_for(model)
    posed = pose_proxy(proxy_bodies(model, proxy, people.betas), people.pose[:, 0]) * 1000
    posed += people.transl[:, 0, None]
    pts = people.keypoints[:, 0].reshape(-1, 3)
    on, off = (
        point_occlusion(cams, posed, proxy.faces, pts, cull_back_faces=True, cell_prefilter=pf)
        for pf in (True, False)
    )
    assert np.isfinite(on.depth).sum() > pts.shape[0]  # surfaces were found: not vacuous
    for name in ("inside", "z", "depth", "owner"):
        np.testing.assert_array_equal(getattr(on, name), getattr(off, name), err_msg=name)
    ids = np.repeat(np.arange(len(posed)), people.keypoints.shape[2])
    assert on.hidden_by_other(ids).any()


def test_no_points_and_points_behind_every_camera():
    rig = dome_rig(3)
    tri = np.array([[[0.0, 0, 0], [100, 0, 0], [0, 100, 0]]])
    empty = point_occlusion(list(rig), tri, np.array([[0, 1, 2]]), np.zeros((0, 3)))
    assert empty.depth.shape == (3, 0)
    far = point_occlusion(list(rig), tri, np.array([[0, 1, 2]]), np.array([[0.0, 0, 1e6]]))
    assert not far.inside.any() and (far.owner == -1).all()
