"""``python -m tactdeform_hw`` is the same as ``tactdeform-hw`` (where the console script is not on PATH)."""

import sys

from tactdeform_hw.cli import main

sys.exit(main())
