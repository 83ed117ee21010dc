"""``python -m gateway.cluster``: etcd and a cluster of gateways on loopback ports (see ``launcher``)."""

import sys

from gateway.cluster.launcher import main

sys.exit(main())
