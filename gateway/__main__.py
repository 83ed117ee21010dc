"""``python -m gateway`` runs the ``psgateway`` command line."""

from gateway.cli import main

raise SystemExit(main())
