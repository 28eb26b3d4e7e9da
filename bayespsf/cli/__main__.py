"""``python -m bayespsf.cli``: the ``bayespsf`` command."""

import sys

from bayespsf.cli import main

sys.exit(main())
