"""mvviz: multi-view, multi-person 3D pose and SMPL reconstruction, and its debugger.

The Python API (:mod:`mvviz.api`) is importable from here; it loads the pipeline only
when a function is called, so ``import mvviz`` stays instant::

    import mvviz
    scene = mvviz.load_scene("sample_data/shelf_synth")
    results = mvviz.run(scene)
    viewer = mvviz.show(scene, results)
"""

__version__ = "0.1.0"

__all__ = ["load_scene", "run", "evaluate", "show", "log_scene", "config_of"]


def __getattr__(name: str):
    if name in __all__:
        from mvviz import api

        return getattr(api, name)
    raise AttributeError(f"module 'mvviz' has no attribute {name!r}")
