"""The SMPL body fit and the VAE pose prior it is corrected by.

- ``smpl``: step I, the fit of the body model to a sequence of 3D tracks by gradient
  descent (:func:`~pipeline.fit.smpl.fit_sequence`); ``chunks``: a long sequence
  fitted in warm-started chunks; ``types``: the fit's settings and result
  (:class:`~pipeline.fit.types.FitParams`, :class:`~pipeline.fit.types.SmplFit`).
- ``prior``: the VAE pose prior (model, loss, checkpoints); ``prior_path``: where the
  shipped prior lies; ``prior_correction``: step II, the fit corrected by the prior.
- ``optim``: the optimiser schedule; ``limit_penalty``: the joint-limit term.

Training the prior is :mod:`pipeline.prior`'s.
May import: ``core``, ``data``, ``importers``, ``body``, ``stages``, ``association``.
"""
