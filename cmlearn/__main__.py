"""``python -m cmlearn`` runs the command line (same as the ``cmlearn`` console script)."""
from .cli import main

raise SystemExit(main())
