"""Tests of the lab (`prdp_petsc.lab`, the demos, the command line, the docs pages).

They need the ``lab`` extra; the library's own tests (``tests/*.py``) need only the
library.  The shared test problems of ``tests/_core.py`` and ``tests/_vector.py`` are
importable here too.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
