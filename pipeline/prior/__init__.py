"""Training the VAE pose prior (:mod:`pipeline.fit.prior` is the model a fit uses).

- ``training``: the training data (the motion library, its perturbations, AMASS and
  BVH files) and the training loop.
- ``sources``: the named pose sources (library, CMU clips, the real Pose2Sim trials)
  with their licences; ``heldout``: checks that evaluation data stays out of training.

May import: every folder up to ``evaluation``.
"""
