"""A run's results as storage: the arrays every stage leaves, their file format and
their cache key; no stage is run from here.

- ``store``: :class:`~pipeline.results.store.PipelineResults`, the per-frame and
  sequence results (:class:`~pipeline.results.store.FrameResult`,
  :class:`~pipeline.results.store.SequenceResult`) packed into columns, the stage names
  (``STAGES``, ``BODY_STAGES``), :func:`~pipeline.results.store.save_results`,
  :func:`~pipeline.results.store.load_results` and the cache key.
- ``array_dir``: a long scene's results as a directory of memory-mapped columns.

May import: every folder up to ``config``.
"""
