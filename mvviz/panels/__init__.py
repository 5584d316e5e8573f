"""The debugger's GUI panels: one module per panel, each ``make_<name>_panel(host)``
returning its controller ``<Name>Panel``, whose ``gui`` is the dataclass ``<Name>Handles``
of its viser handles (``view_panels``: timeline, layers, selection, camera; then
``pipeline_panel``, ``filter_panel``, ``failure_panel``, ``export_panel``).

A panel is built against :class:`mvviz.panels.contract.PanelHost` (the viewer state,
``set_results``, ``show_data``, ``jump_to``, ``subscribe``, ``stopped``, ...), never against
the app, so a panel can be tested with a fake host (``tests/mvviz/panels/test_contract.py``);
the app (:mod:`mvviz.app`) builds every panel, owns its lifecycle and stops it
(:class:`~mvviz.panels.contract.Panel`). Panels may import :mod:`mvviz.state`,
:mod:`mvviz.scene`, :mod:`mvviz.analysis`, :mod:`mvviz.export`, :mod:`mvviz.workers` and
``pipeline``; never :mod:`mvviz.app` or :mod:`mvviz.cli` (``tests/test_structure.py`` checks).
"""
