"""The gRPC gateway: router, listen hub, proxies, config and CLI."""
