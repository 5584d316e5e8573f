"""The numpy side of the body model (pipeline/body/arrays.py) agrees with the torch model
it feeds (the viewer skins with it; the fit runs the torch one)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.body.arrays import load_body_model_data
from pipeline.body.model import BodyModel, rigid_chain, torch_body_model
from pipeline.core.rotations import axis_angle_to_matrix


def test_numpy_forward_kinematics_and_shape_match_torch():
    data = load_body_model_data()
    model = torch_body_model(data)
    assert isinstance(model, BodyModel) and model.data is data
    assert torch_body_model(data) is model  # built once
    assert model.fingerprint == data.fingerprint
    rng = np.random.default_rng(3)
    pose = rng.normal(0, 0.4, (5, 24, 3))
    betas = rng.normal(0, 1.0, (5, 7))  # fewer betas than the model has: zero-padded
    R_np, posed_np = data.pose_chain(pose, betas)
    with torch.no_grad():
        b = torch.nn.functional.pad(torch.as_tensor(betas, dtype=torch.float32), (0, 3))
        rest = model.rest_joints(b)
        posed_t, T = rigid_chain(
            axis_angle_to_matrix(torch.as_tensor(pose, dtype=torch.float32)), rest, model.tree
        )
        verts_t = model(torch.zeros(5, 72), b).vertices.numpy()
    np.testing.assert_allclose(R_np, T[..., :3, :3].numpy(), atol=2e-5)
    np.testing.assert_allclose(posed_np, posed_t.numpy(), atol=2e-5)  # metres
    np.testing.assert_allclose(data.rest_joints(betas), rest.numpy(), atol=2e-5)
    # the rest pose of LBS is the shaped template (the open model has no pose blend shapes)
    np.testing.assert_allclose(data.shaped_vertices(betas), verts_t, atol=2e-5)
    assert posed_np.std() > 0.1  # a real pose, not the rest pose


@pytest.mark.parametrize("betas", [np.zeros((1, 10)), np.ones((1, 12))])
def test_padded_betas(betas):
    data = load_body_model_data()
    assert data.padded_betas(betas).shape == (1, data.num_betas)
