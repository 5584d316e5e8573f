"""Check `mvviz export`'s BVH and GLB in Blender itself (Blender as a Python module).

Not part of the tests: ``bpy`` is a ~350 MB wheel, so this runs in its own venv::

    python -m venv /tmp/bpyenv && /tmp/bpyenv/bin/pip install "bpy==4.5.*"
    mvviz export SCENE --format bvh --track 0 -o out/t0.bvh
    mvviz export SCENE --format glb -o out/all.glb
    python tools/blender_check_exports.py --reference SCENE out/ref.npz   # our env: fitted joints
    /tmp/bpyenv/bin/python tools/blender_check_exports.py out/ref.npz out/t0.bvh out/all.glb

Blender imports the BVH (File > Import > Motion Capture defaults: -Z forward, Y up) and
the GLB (its glTF importer), plays them to frames 0, 100 and the last, and compares
track 0's bone heads and tracks 0 and 1's deformed vertices with the fit (Blender's
axes: ``(y, -x, z)`` of our world, metres).
"""

from __future__ import annotations

import sys

import numpy as np


def write_reference(scene_dir: str, out: str) -> None:
    from pipeline.body.model import load_body_model
    from pipeline.config import PipelineConfig
    from pipeline.data.scene import load_scene
    from pipeline.run.pipeline import run_or_load

    model = load_body_model()
    scene = load_scene(scene_dir)
    res, _ = run_or_load(scene, PipelineConfig(), model, progress=False)
    fit = res.smpl_vae if res.smpl_vae is not None else res.smpl
    frames = [0, min(100, res.num_frames - 1), res.num_frames - 1]
    np.savez(
        out,
        joints=fit.joints[0][frames],
        verts0=np.stack([fit.vertices(0, f) for f in frames]),
        verts1=np.stack([fit.vertices(1, f) for f in frames]),
        frames=np.array(frames),
        names=np.array(model.joint_names),
        fps=scene.fps,
    )


def to_blender(p_mm: np.ndarray) -> np.ndarray:
    p = np.asarray(p_mm) / 1000.0
    return np.stack([p[..., 1], -p[..., 0], p[..., 2]], -1)


def check(ref_path: str, bvh: str, glb: str) -> None:
    import bpy

    ref = np.load(ref_path)
    names = [str(n) for n in ref["names"]]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_anim.bvh(filepath=bvh, update_scene_fps=True, update_scene_duration=True)
    sc = bpy.context.scene
    arm = next(o for o in sc.objects if o.type == "ARMATURE")
    err = 0.0
    for i, f in enumerate(ref["frames"]):
        sc.frame_set(int(f) + 1)  # the BVH importer starts at frame 1
        got = np.array([list(arm.matrix_world @ arm.pose.bones[n].head) for n in names])
        err = max(err, np.linalg.norm(got - to_blender(ref["joints"][i]), axis=-1).max())
    print(f"BVH: {len(arm.data.bones)} bones, frames {tuple(arm.animation_data.action.frame_range)}"
          f", fps {sc.render.fps}; max bone-head error {1000 * err:.3f} mm")  # fmt: skip
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.context.scene.render.fps = int(round(float(ref["fps"])))
    bpy.ops.import_scene.gltf(filepath=glb)
    sc = bpy.context.scene
    bodies = {o.name: o for o in sc.objects if o.type == "MESH" and o.name.endswith("_body")}
    arms = [o for o in sc.objects if o.type == "ARMATURE"]
    med = worst = 0.0
    for i, f in enumerate(ref["frames"]):
        sc.frame_set(int(f))  # glTF time 0 = frame 0
        dg = bpy.context.evaluated_depsgraph_get()
        for name, key in (("track0_body", "verts0"), ("track1_body", "verts1")):
            ev = bodies[name].evaluated_get(dg)
            mesh = ev.to_mesh()
            v = np.array([list(ev.matrix_world @ p.co) for p in mesh.vertices])
            ev.to_mesh_clear()
            e = np.linalg.norm(v - to_blender(ref[key][i]), axis=-1)
            med, worst = max(med, float(np.median(e))), max(worst, float(e.max()))
    print(f"GLB: {len(arms)} armatures, {len(bodies)} bodies; deformed vertices vs the fit: "
          f"median {1000 * med:.4f} mm, max {1000 * worst:.3f} mm")  # fmt: skip


if __name__ == "__main__":
    if sys.argv[1] == "--reference":
        write_reference(sys.argv[2], sys.argv[3])
    else:
        check(*sys.argv[1:4])
