"""``python -m gateway`` runs the ``psgateway`` command line."""

try:
    from gateway.cli import main
except KeyboardInterrupt:  # Ctrl-C while the modules load: a clean exit, as later (128 + SIGINT)
    raise SystemExit(130) from None

raise SystemExit(main())
