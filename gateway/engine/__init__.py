"""The protocol-neutral engine: plain request, reply and event types, and the parts that work in them."""
