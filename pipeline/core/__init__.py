"""Foundations every other folder stands on; imports nothing else of ``pipeline``.

- ``files``: atomic writes, the scene format's error
  (:class:`~pipeline.core.files.SceneFormatError`, one line naming file and field),
  npz reading and writing, the cache folder.
- ``schema``: JSON field checks; ``units``: millimetres per metre and the repository's
  own paths (one home for each); ``progress``: progress bars and callbacks;
  ``npy_stream``: memory-mapped columns written row by row; ``torch_threads``: the
  thread count torch runs with; ``assignment``: minimum-cost matching;
  ``rotations``: axis-angle and matrix conversions (NumPy); ``palette``: track colours.
"""
