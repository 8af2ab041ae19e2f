"""``python -m host.cli``: the same as the ``upright`` console script."""

import sys

from host.cli.main import main

sys.exit(main())
