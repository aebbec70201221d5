"""``python -m jaxmpm ...``: the same as the ``jaxmpm`` command (see :mod:`jaxmpm.cli`)."""

from .cli import main

raise SystemExit(main())
