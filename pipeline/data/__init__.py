"""What a scene is: cameras, joint sets, detections, ground truth and reference tracks.

- ``scene``: the native scene format (:func:`~pipeline.data.scene.load_scene`,
  :func:`~pipeline.data.scene.write_scene`) and its checks.
- ``cameras``: the calibrated rig (OpenCV model, world millimetres, z up).
- ``joint_sets``: every 2D/3D joint layout by name and the mappings between them.
- ``references``: other tools' 3D results stored beside a scene.

May import: ``core``.
"""
