"""The debugger's GUI panels: one module per panel (its handles, its controller).

A panel is built against :class:`mvviz.panels.contract.PanelHost` (the viewer state,
``set_results``, ``jump_to``, ``subscribe``, ``stopped``), never against the app, so a
panel can be tested with a fake host; the app (:mod:`mvviz.app`) builds every panel,
owns its lifecycle and stops it. Panels may import :mod:`mvviz.state`, :mod:`mvviz.scene`,
:mod:`mvviz.analysis`, :mod:`mvviz.export`, :mod:`mvviz.workers` and ``pipeline``; never
:mod:`mvviz.app` or :mod:`mvviz.cli` (``tests/test_structure.py`` checks).
"""
