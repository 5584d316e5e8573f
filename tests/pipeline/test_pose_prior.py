"""pipeline.fit.prior: the shipped VAE against held-out poses and a broken wrist;
training, checkpoints (weights_only), AMASS-style data and the train-prior command."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mvviz.cli import main
from pipeline.body import pose_limits
from pipeline.fit.prior import BODY_JOINTS, DEFAULT_PRIOR_PATH, load_prior, save_prior
from pipeline.prior.training import load_pose_data, perturb_poses, train_prior
from pipeline.synth.motion import sample_pose_library

BODY = list(BODY_JOINTS)


@pytest.fixture(scope="module")
def prior():
    return load_prior()


def mean_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Mean geodesic distance over the body joints of (N, 24, 3) poses, degrees."""
    ra = Rotation.from_rotvec(a[:, BODY].reshape(-1, 3))
    rb = Rotation.from_rotvec(b[:, BODY].reshape(-1, 3))
    return float(np.rad2deg((ra.inv() * rb).magnitude()).mean())


def chordal_mean(poses: np.ndarray) -> np.ndarray:
    """(24, 3) per-joint rotation mean of (N, 24, 3) poses."""
    return np.stack([Rotation.from_rotvec(poses[:, j]).mean().as_rotvec() for j in range(24)])


def test_shipped_checkpoint_is_small_and_records_its_training():
    assert DEFAULT_PRIOR_PATH.is_file()
    assert DEFAULT_PRIOR_PATH.stat().st_size < 2e6
    ckpt = torch.load(DEFAULT_PRIOR_PATH, map_location="cpu", weights_only=True)
    assert ckpt["info"]["num_poses"] > 0 and ckpt["info"]["holdout_reconstruction"] > 0
    assert ckpt["config"]["epochs"] > 0 and ckpt["config"]["latent"] > 0


def test_reconstructs_held_out_poses_better_than_the_mean_pose(prior):
    train = sample_pose_library(4000, seed=0).reshape(-1, 24, 3)
    held_out = sample_pose_library(1000, seed=12345).reshape(-1, 24, 3)  # another seed
    rec = prior.reconstruct(held_out)
    mean = np.broadcast_to(chordal_mean(train), held_out.shape)
    err_vae, err_mean = mean_angle_deg(rec, held_out), mean_angle_deg(mean, held_out)
    # measured: 1.5 deg (VAE) against 11.7 deg (mean pose)
    assert err_vae < 4.0 and err_vae < 0.4 * err_mean
    np.testing.assert_array_equal(rec[:, 0], held_out[:, 0])  # the root is kept


def test_prior_pulls_a_broken_wrist_back(prior):
    poses = sample_pose_library(200, seed=7).reshape(-1, 24, 3)
    ang = pose_limits.swing_twist(poses)
    ang[:, pose_limits.J["left_wrist"], 0] = np.deg2rad(-125.0)  # flexed 45 deg past -80
    broken = pose_limits.from_swing_twist(ang)
    wrist = pose_limits.J["left_wrist"]
    before = pose_limits.limit_excess(broken)[:, wrist]
    after = pose_limits.limit_excess(prior.reconstruct(broken))[:, wrist]
    np.testing.assert_allclose(before, 45.0, atol=1e-6)
    assert after.mean() < 0.2 * before.mean()
    assert (after < before).all()


def test_decoded_samples_are_plausible(prior):
    z = torch.randn(1000, prior.latent, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        R = prior.decode_rotmats(z).double().numpy()
    poses = np.zeros((1000, 24, 3))
    poses[:, 1:] = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(1000, 23, 3)
    assert pose_limits.violations_per_1000(poses) < 20.0


def test_perturbations_stay_inside_the_limits():
    lib = sample_pose_library(500, seed=3)
    out = perturb_poses(lib, np.random.default_rng(0)).reshape(-1, 24, 3)
    assert len(out) > 100
    assert pose_limits.limit_excess(out).max() == 0.0
    # the joints the library never moves now move
    wrist = pose_limits.J["right_wrist"]
    assert np.abs(out[:, wrist]).max() > 0.3


def test_train_save_load_round_trip(tmp_path):
    poses = sample_pose_library(600, seed=1)
    prior = train_prior(poses, epochs=2, latent=8, hidden=32, progress=False, seed=3)
    path = tmp_path / "p.pt"
    save_prior(prior, path)
    back = load_prior(path)
    assert back.config == prior.config and back.info["num_poses"] == 600
    x = poses[:20].reshape(-1, 24, 3)
    np.testing.assert_allclose(back.reconstruct(x), prior.reconstruct(x), atol=1e-6)
    again = train_prior(poses, epochs=2, latent=8, hidden=32, progress=False, seed=3)
    np.testing.assert_allclose(again.reconstruct(x), prior.reconstruct(x), atol=1e-6)  # seeded


def test_amass_layout_and_cli(tmp_path):
    rng = np.random.default_rng(0)
    smplh = np.zeros((300, 156))
    smplh[:, :72] = sample_pose_library(300, seed=2)
    smplh[:, 72:] = rng.normal(0, 0.3, (300, 84))  # finger joints: ignored
    np.savez(tmp_path / "a.npz", poses=smplh, betas=np.zeros(16))
    np.testing.assert_array_equal(load_pose_data(tmp_path / "a.npz"), smplh[:, :72])
    np.savez(tmp_path / "bad.npz", trans=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="poses"):
        load_pose_data(tmp_path / "bad.npz")
    out = tmp_path / "cli.pt"
    args = ["train-prior", "--data", str(tmp_path / "a.npz"), "--out", str(out), "--epochs", "1"]
    assert main(args + ["--latent", "4", "--hidden", "16"]) == 0
    prior = load_prior(out)
    assert prior.config.latent == 4 and str(tmp_path / "a.npz") in prior.info["data"]


@pytest.mark.slow
def test_the_fit_side_loads_no_training_modules():
    """Importing the prior and reading the shipped checkpoint, what every fit does (a
    batch worker before its first scene), loads neither the motion library nor the BVH
    importers (~0.2 s of a worker's warm-up); the training functions import them."""
    import subprocess
    import sys

    from tests.conftest import REPO

    code = (
        "import sys\n"
        "from pipeline.fit.prior import load_prior\n"
        "load_prior(None)\n"
        "print(sorted(m for m in sys.modules"
        " if m in ('pipeline.mocap.clips', 'pipeline.synth.motion')"
        " or m.startswith('pipeline.importers')))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO
    ).stdout
    assert out.strip() == "[]"
