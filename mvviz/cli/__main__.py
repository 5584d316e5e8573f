"""``python -m mvviz.cli``: the same command line as the ``mvviz`` script."""

import sys

from mvviz.cli import main

sys.exit(main())
