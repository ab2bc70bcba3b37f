"""``python -m benchmarks [--quick] [--only NAMES] [--out DIR]``: the same as
``python benchmarks/run_all.py`` (run from the repository's root; benchmarks/ is a
folder of scripts, not an installed package)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from run_all import main  # noqa: E402

sys.exit(main())
