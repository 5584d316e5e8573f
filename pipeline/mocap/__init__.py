"""Motion-capture clips (BVH) as body motion: read, retargeted and fitted with the body
model (``clips``), for synthetic scenes and for the pose prior's training data.

May import: every folder up to ``fit``.
"""
