"""The viewer's outputs to other tools: rerun recordings, written to a file
(``rrd``: ``mvviz export-rrd``) or live beside the viewer (``rerun_live``), both with
the one entity layout of :mod:`mvviz.export.rerun`. (The file formats of ``mvviz
export`` — TRC, C3D, BVH, SMPL npz, GLB — are pure functions in ``pipeline.exports``.)
May import :mod:`mvviz.scene` and ``pipeline``; never the panels or the command line
(``rerun_live`` reads the running app through the panel contract).
"""
