"""`python -m renderer ...` is `rayfarm render ...` without the service layer."""

from .cli import main

raise SystemExit(main())
