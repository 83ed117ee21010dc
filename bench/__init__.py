"""The benchmark: the gateway beside a bare grpc.aio server of the same contract.

Run ``python -m bench --help``. Each server runs in its own process, one at a
time; the load generator (this package's ``__main__``) drives both through the
generated stubs, so the two are measured with exactly the same client code.
Parts (e)-(h) measure the line-protocol proxy beside a direct line client
(``bench.line``), group moveto and registry find in-process (``bench.groups``),
and registration of many raw-TCP devices (``bench.register``, with the devices
in ``bench.device_farm`` processes).
"""
