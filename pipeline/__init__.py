"""mvviz processing pipeline: pure functions over shape-documented numpy/torch arrays.

Units: millimetres in the world (z up, floor at z = 0), pixels in images, metres
inside the body model. Each stage lives in its own module and returns a frozen
dataclass; the folders say what they hold, lowest first: ``core``, ``data``,
``importers``, ``calibrate``, ``body``, ``stages``, ``association``, ``fit``, ``mocap``, ``synth``,
``config`` (the module of every stage's settings), ``results``, ``run``,
``evaluation``, ``prior``, ``detect``, ``exports``, ``diagnose``, ``batch``. A folder
imports only from itself and those before it (``tests/test_structure.py`` checks it);
:mod:`pipeline.run` is the one place that composes the stages.

Entry points for scripts: :func:`pipeline.data.scene.load_scene`,
:func:`pipeline.run.pipeline.run_pipeline`, :func:`pipeline.run.pipeline.run_or_load`,
:func:`pipeline.results.store.load_results`.
"""
