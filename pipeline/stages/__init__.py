"""The per-frame and sequence stages between detections and bodies, one module each.

- ``restore``: 2D restoration of missed joints from the body model.
- ``triangulate``: confidence-weighted DLT per person, outlier views rejected.
- ``track``: people linked over frames into tracks.
- ``stitch``: the tracks of one person joined over the whole run.
- ``proportions``: joints that contradict their track's bones re-solved or flagged.
- ``kalman``: the per-joint Kalman filter and RTS smoother over tracks.
- ``retime``: per-camera time offsets applied to detections (a re-timed camera's rows).

Cross-view association is its own folder (:mod:`pipeline.association`).
May import: ``core``, ``data``, ``importers``, ``body``.
"""
