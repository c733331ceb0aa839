"""``python -m prdp_petsc.lab.cli``: the ``prdp-petsc`` command."""

from . import main

raise SystemExit(main())
