"""Synthetic scenes: people with known ground truth seen by a calibrated rig.

- ``scene_gen``: a whole scene (motion, bodies, detections with a detector's errors,
  occlusion, pictures) written in the native format; ``mocap_scene``: the same driven
  by motion-capture clips.
- ``motion``: the procedural motion library (activities and their poses); ``rigs``:
  camera rings and domes; ``render``: pictures of bodies; ``occlusion``: who hides whom.
- ``detectors``: simulated 2D detectors (noise, misses, left/right swaps, ghosts);
  ``detection_rows`` and ``detection_stats``: their rows and statistics; ``proxy``:
  cheap stand-in bodies for big scenes.

May import: every folder up to ``mocap``.
"""
