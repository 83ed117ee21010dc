"""The front ends: each speaks one protocol and calls the engine in plain types."""
