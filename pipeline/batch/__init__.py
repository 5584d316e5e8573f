"""Many scenes, many machines: the pipeline over a dataset on Ray (``mvviz batch``).

- :mod:`pipeline.batch.jobs`: the work, as pure functions (no Ray): a scene's inputs,
  the per-frame stages of one frame chunk, the join (sequence stages, SMPL fit), the
  summary a report needs (metrics, worst moments); a result is current when its file
  carries :func:`pipeline.results.store.cache_key` of the job (the key ``mvviz run`` uses).
- :mod:`pipeline.batch.ray_run`: those functions as Ray tasks, embedded local Ray or a
  cluster, retries, progress over scenes and chunks.
- :mod:`pipeline.batch.sweep`: ``--sweep SECTION.FIELD=V1,V2`` grids.
- :mod:`pipeline.batch.report`: ``batch_report.json`` and the self-contained
  ``batch_report.html``.
"""
