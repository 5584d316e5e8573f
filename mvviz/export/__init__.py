"""The viewer's outputs to other tools: rerun recordings, written to a file
(``rrd``: ``mvviz export-rrd``) or live beside the viewer (``rerun_live``), both with
the one entity layout of :mod:`mvviz.export.rerun`. (The file formats of ``mvviz
export`` — TRC, C3D, BVH, SMPL npz, GLB — are pure functions in ``pipeline.exports``.)
May import :mod:`mvviz.state`, :mod:`mvviz.scene`, :mod:`mvviz.analysis` and ``pipeline``;
never the panels, the app or the command line
(``rerun_live`` reads the running viewer through a part of the panel contract,
:class:`~mvviz.export.rerun_live.LiveHost`, declared there).
"""
