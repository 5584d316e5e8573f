"""mvviz processing pipeline: pure functions over shape-documented numpy/torch arrays.

Units: millimetres in the world (z up, floor at z = 0), pixels in images, metres
inside the body model. Each stage lives in its own module and returns a frozen
dataclass; :mod:`pipeline.run.frames` composes them.
"""
