"""The gateway's Prometheus metrics: plain counters on the hot paths, read at scrape time.

``counts`` holds the counters the calls raise (no prometheus_client import);
``collector`` turns every counter and gauge of a gateway into metric families;
``endpoint`` serves them as ``/metrics``. docs/metrics.md lists every metric.
"""
