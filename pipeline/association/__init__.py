"""Cross-view association: which detections of one frame are one person.

- ``associate``: the stage (:func:`~pipeline.association.associate.associate_frame`).
- ``params``: its settings (:class:`~pipeline.association.params.AssociationParams`).
- ``affinity``: ray-to-ray distances between detections and the average linkage;
  ``pairs``: the blocked kernels behind them; ``fused``: the same in one compiled
  (numba) pass for big frames.
- ``refine``: splitting, merging and moving detections after the linkage.
- ``flips``: left/right-mirrored detections found and un-mirrored.

May import: ``core``, ``data``, ``importers``, ``body``, ``stages``.
"""
