"""``python -m ngp_warp.cli`` (as torchrun runs the command)."""

import sys

from ngp_warp.cli import main

sys.exit(main())
