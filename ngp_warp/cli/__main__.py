"""``python -m ngp_warp.cli`` (as ``--gpus`` and torchrun run the ranks)."""

import sys

from ngp_warp.cli import main

sys.exit(main())
