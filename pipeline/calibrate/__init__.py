"""Camera calibration from a ChArUco or checkerboard board walked through the views.

:mod:`~pipeline.calibrate.board` (the board and its detection in one image),
:mod:`~pipeline.calibrate.footage` (the frames of each camera, matched across cameras),
:mod:`~pipeline.calibrate.intrinsics` (each camera's K and distortion),
:mod:`~pipeline.calibrate.extrinsics` (board poses, camera pairs, the bundle adjustment
with the board's motion and each camera's time offset),
:mod:`~pipeline.calibrate.world` (the world frame: the first camera, or the board on the
floor), :mod:`~pipeline.calibrate.report` (the report page) and
:mod:`~pipeline.calibrate.calibrate`, which composes them into a
:class:`~pipeline.data.cameras.CameraRig`.

Units: board geometry and the world in millimetres, images in pixels. Imports from
``core``, ``data`` and ``importers`` only.
"""
