"""The body model and what is computed from it, without fitting.

- ``model``: the SMPL-layout body model in torch (forward kinematics, skinning);
  ``arrays``: the same model's arrays, read without torch.
- ``kinematics``: 6D / axis-angle rotations and the keypoints of a posed body;
  ``keypoints``: how each joint set's keypoints are regressed from the body, and which
  sets a fit can target (``FITTABLE_JOINT_SETS``).
- ``pose_limits``: anatomical joint limits (swing-twist boxes); ``measures``: bone lengths
  and body proportions.

May import: ``core``, ``data``, ``importers``.
"""
