"""``python -m ddh_vsensor``: the ``ddh-vsensor`` command without its script."""

import sys

from ddh_vsensor.cli.main import main

sys.exit(main())
