"""``python -m tactdeform_hw.cli`` is the same as ``tactdeform-hw``."""

import sys

from . import main

sys.exit(main())
