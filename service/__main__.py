"""`python -m service ...` is the `rayfarm` command."""

from .cli import main

raise SystemExit(main())
