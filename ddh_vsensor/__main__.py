"""``python -m ddh_vsensor``: the ``ddh-vsensor`` command without its script."""

import sys

from .cli.main import main

sys.exit(main())
