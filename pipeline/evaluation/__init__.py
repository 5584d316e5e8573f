"""How good results are: metrics (MPJPE, PCK, PCP, jitter, association and identity
scores; ``metrics``), the evaluation of every stage against ground truth
(``evaluate``) and the plausibility check of keypoint labels (``label_check``).

May import: every folder up to ``run``.
"""
