"""``python -m mvviz.cli``: the same command line as the ``mvviz`` script."""

from mvviz.cli import entry

entry()
