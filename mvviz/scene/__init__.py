"""Drawing the scene: what the viewer puts in the 3D view and on the camera images.

``geometry`` turns a scene and its results into plain per-frame arrays
(:class:`~mvviz.scene.geometry.ViewerData`, skeleton segments, rays, colours); ``bodies``,
``decimate`` and ``skinned`` the SMPL meshes (fitted and ground truth, display
resolution, bulk bone posing); ``layers`` the viser scene nodes; ``images`` the camera
frames and their 2D overlays. May import :mod:`mvviz.workers` and ``pipeline``; never the
panels, the app or the command line.
"""
