"""``python -m benchmarks [--quick] [--json] [--only NAME...]``: every benchmark, one table.

See benchmarks/suite.py (also ``bsc bench``).
"""
import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from benchmarks.suite import main  # noqa: E402

sys.exit(main())
