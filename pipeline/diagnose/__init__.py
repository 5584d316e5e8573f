"""Diagnosis of a capture, from the data itself: what is wrong with the user's cameras,
not with the pipeline's math.

``reference`` re-triangulates every track without one camera (the other cameras'
view of where each joint is); ``sync`` finds a camera's time offset from it (whole and
sub-frame, with a residual curve and a confidence); ``calibration`` the per-camera
reprojection residual as a field over the image and over time, a moved camera, and a
bundle adjustment of a suspect camera's pose; ``floor`` the floor plane and the up
axis. Pure functions over a :class:`~pipeline.data.scene.Scene` and its
:class:`~pipeline.results.store.PipelineResults`; ``mvviz diagnose`` prints them.
"""
