"""``python -m lrmfrf.cli``: the ``lrmfrf`` command."""

from . import main

raise SystemExit(main())
