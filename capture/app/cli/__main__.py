"""``python -m capture.app.cli``: the same as the ``perfcap`` console script."""

import sys

from capture.app.cli import main

sys.exit(main())
