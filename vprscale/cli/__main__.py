"""``python -m vprscale.cli``: what pipelines and tests spawn, the same as the ``vprscale`` script."""

import sys

from vprscale.cli import main

sys.exit(main())
