"""The test suite executes every notebook (nbmake) at quick sizes: ``SPACEGRASP_NOTEBOOK_QUICK=1``
unless the caller set it. ``notebooks/run_full.sh`` sets it to 0 to regenerate the committed
full-size outputs. The kernels inherit this process's environment."""

import os

os.environ.setdefault("SPACEGRASP_NOTEBOOK_QUICK", "1")
