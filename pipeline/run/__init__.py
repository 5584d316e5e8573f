"""The one place where the stages are composed.

- ``pipeline``: the whole run, :func:`~pipeline.run.pipeline.run_pipeline` (scene in,
  results out) and :func:`~pipeline.run.pipeline.run_or_load` (with the cache).
- ``frames``: the per-frame stages (restored 2D, association, triangulation) and the
  sequence stages (tracking, filtering) as steps.
- ``chunked``: frames packed into columns as they are done (the in-memory run, the
  viewer's partial re-runs, the batch); ``streamed``: a long scene's columns written to
  disk as they go.
- ``bodies``: the SMPL fits on packed results.

May import: every folder up to ``results``.
"""
