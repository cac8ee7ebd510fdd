"""``python -m chic_design.cli``: the ``chic-design`` program."""

import sys

from chic_design.cli.main import main

sys.exit(main())
