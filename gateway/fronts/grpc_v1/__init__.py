"""The gRPC front of contract v1: the only place protobuf messages are built or read."""
