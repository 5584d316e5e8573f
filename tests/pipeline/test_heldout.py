"""The held-out protocol (pipeline/prior/heldout.py) and the safety of the prior's correction
on motion the prior has not seen."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.data.scene import load_scene
from pipeline.evaluation.evaluate import evaluate
from pipeline.fit.prior import load_prior, save_prior
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.prior.heldout import (
    check_activity_held_out,
    check_disjoint,
    scene_frames,
    training_frames,
)
from pipeline.prior.sources import sources_for, train_on
from pipeline.run.pipeline import run_or_load
from pipeline.synth.mocap_scene import MocapSceneConfig, write_mocap_scene
from tests.conftest import REPO

pytestmark = pytest.mark.slow

CMU = REPO / "sample_data" / "mocap" / "cmu131"


@pytest.fixture(scope="module")
def hop_scene(tmp_path_factory):
    """One person hopping (CMU 131_03), 30 frames, campus rig, default detector noise."""
    out = tmp_path_factory.mktemp("heldout") / "hop"
    rig = read_voxelpose_calibration(REPO / "sample_data" / "rigs" / "campus_voxelpose.json")
    config = MocapSceneConfig(motions=(str(CMU / "131_03.bvh"),), num_people=1, num_frames=30,
                              seed=1)  # fmt: skip
    write_mocap_scene(out, rig, load_body_model(), config, progress=False)
    return out


@pytest.fixture(scope="module")
def prior_without_hop(tmp_path_factory):
    """A prior that never saw hopping: the library and the balancing trial, fewer poses and
    epochs than the shipped one (the CMU clips left out whole: their fit takes minutes)."""
    sources = sources_for(exclude_sources=("cmu",), exclude_activities=("hop",), num_poses=12000)
    path = tmp_path_factory.mktemp("prior") / "no_hop.pt"
    save_prior(train_on(sources, epochs=20, progress=False), path)
    return path


def _bvh_source(name: str, frames: int) -> dict:
    return {"file": f"sample_data/mocap/cmu131/{name}", "source_frames": frames}


def test_split_frames_are_disjoint_or_refused(hop_scene):
    synth = json.loads((hop_scene / "scene.json").read_text())["synth"]
    test = scene_frames(synth)
    (person,) = synth["people"]
    # 30 scene frames at 25 fps cover 29 x 4.8 + 1 = 140 file frames at 120 fps
    assert {f for f, _ in test} == {"131_03.bvh"}
    first = int(np.floor(person["start_frame"] * 120 / 25))
    assert min(i for _, i in test) == first and 135 <= len(test) <= 145
    walks = [_bvh_source("131_01.bvh", 994), _bvh_source("131_02.bvh", 1000),
             {"file": "synthetic library", "frames": 40000}]  # fmt: skip
    assert not (training_frames(walks) & test)
    check_disjoint(walks, synth)  # passes: the walks never play the hop
    with pytest.raises(ValueError, match="131_03"):
        check_disjoint(walks + [_bvh_source("131_03.bvh", 1102)], synth)
    # a clip sharing the name but covering only frames before the scene's is disjoint
    check_disjoint([_bvh_source("131_03.bvh", first)], synth)


def test_prior_correction_is_safe_on_held_out_motion(hop_scene, prior_without_hop):
    """A prior that never saw the hop: SMPL + VAE within 1 mm of step I on the measured
    joints, no worse on the SMPL joints, no more hinge violations, few limit violations."""
    prior = load_prior(prior_without_hop)
    synth = json.loads((hop_scene / "scene.json").read_text())["synth"]
    check_disjoint(prior.info["sources"], synth)
    check_activity_held_out(prior.info["sources"], "hop")
    with pytest.raises(ValueError, match="131_03"):  # the shipped prior saw the hop
        check_disjoint(load_prior().info["sources"], synth)
    scene = load_scene(hop_scene)
    config = PipelineConfig(pose_prior=str(prior_without_hop))
    results, _ = run_or_load(scene, config, load_body_model(), progress=False)
    ev = evaluate(scene, results)
    rts, step1, vae = (ev.stages[k]["mpjpe"] for k in ("rts", "smpl", "smpl_vae"))
    pl = ev.plausibility
    assert step1 <= rts + 5.0, (rts, step1)
    assert vae <= step1 + 1.0, (step1, vae)
    assert ev.smpl24["smpl_vae"]["mpjpe"] <= ev.smpl24["smpl"]["mpjpe"]
    assert pl["smpl"]["limit_violations_per_1000"] <= 50.0
    assert pl["smpl_vae"]["limit_violations_per_1000"] <= 5.0
    assert pl["smpl_vae"]["hinge_violations_per_1000"] <= pl["smpl"]["hinge_violations_per_1000"]
    print(f"rts {rts:.1f} step I {step1:.1f} vae {vae:.1f} mm")
