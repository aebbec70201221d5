"""``python -m jaxmpm ...``: the same as the ``jaxmpm`` command (see :mod:`jaxmpm.cli`)."""

from .cli import main

if __name__ == "__main__":  # importing the module (an API-reference build) runs nothing
    raise SystemExit(main())
