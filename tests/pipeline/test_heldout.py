"""The held-out protocol (pipeline/heldout.py) and the safety of the prior's correction
on motion the prior has not seen (issue 19)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mvviz.cli import main
from pipeline.body_model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.evaluate import evaluate
from pipeline.heldout import check_disjoint, scene_frames, training_frames
from pipeline.pose_prior import load_prior
from pipeline.results import run_or_load
from pipeline.scene import load_scene
from tests.conftest import REPO

CMU = REPO / "sample_data" / "mocap" / "cmu131"


@pytest.fixture(scope="module")
def hop_scene(tmp_path_factory):
    """One person hopping (CMU 131_03), 30 frames, campus rig, default detector noise."""
    out = tmp_path_factory.mktemp("heldout") / "hop"
    args = ["synth", str(out), "--motion", str(CMU / "131_03.bvh"), "--rig", "campus",
            "--people", "1", "--frames", "30", "--seed", "1"]  # fmt: skip
    assert main(args) == 0
    return out


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


def test_prior_correction_is_safe_on_held_out_motion(hop_scene):
    """The shipped prior is trained without the hop clip; SMPL + VAE stays within 1 mm
    of step I on the measured joints, no worse on the SMPL joints, few limit violations."""
    prior = load_prior()
    synth = json.loads((hop_scene / "scene.json").read_text())["synth"]
    check_disjoint(prior.info.get("sources", []), synth)
    scene = load_scene(hop_scene)
    results, _ = run_or_load(scene, PipelineConfig(), load_body_model(), progress=False)
    ev = evaluate(scene, results)
    rts, step1, vae = (ev.stages[k]["mpjpe"] for k in ("rts", "smpl", "smpl_vae"))
    assert step1 <= rts + 5.0, (rts, step1)
    assert vae <= step1 + 1.0, (step1, vae)
    assert ev.smpl24["smpl_vae"]["mpjpe"] <= ev.smpl24["smpl"]["mpjpe"] + 0.5
    assert ev.plausibility["smpl"]["limit_violations_per_1000"] <= 50.0
    assert ev.plausibility["smpl_vae"]["limit_violations_per_1000"] <= 5.0
    print(f"rts {rts:.1f} step I {step1:.1f} vae {vae:.1f} mm")
