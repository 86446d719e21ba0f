"""``python -m closedchain``: the command-line tool (same as the ``closedchain`` script)."""

from .cli import main

raise SystemExit(main())
