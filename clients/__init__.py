"""Python client SDK (sync and asyncio) and the ``psctl`` command line."""
