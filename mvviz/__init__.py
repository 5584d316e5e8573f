"""mvviz viewer: a viser scene and its panels, reading pipeline results."""

__version__ = "0.1.0"
