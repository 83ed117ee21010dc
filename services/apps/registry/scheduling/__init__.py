"""The registry's scheduler: which providers serve a consumer's request, under licences.

Sans-IO core, one concept a module: ``capabilities`` (names and sets), ``cover`` (the smallest
set of providers covering a capability set: exact up to :data:`EXACT_LIMIT` capabilities, greedy
beyond), ``cost`` (drive distance, odometry, ranking by cost and QoS), ``qos`` (the assessments
per provider), ``queue`` (requests waiting for a busy provider), ``model`` (the records),
``scheduler`` (rules (a)–(f) and the five steps). The registry wires it to its table, the
licences and the clock in ``services.apps.registry.dispatch``.
"""

from services.apps.registry.scheduling.capabilities import (
    MAX_CAPABILITIES,
    check_capabilities,
    parse_capabilities,
)
from services.apps.registry.scheduling.cost import (
    DEFAULT_QOS,
    DEFAULT_WEIGHT,
    drive_distance,
    odometry_distance,
    rank_scores,
)
from services.apps.registry.scheduling.cover import EXACT_LIMIT, cover, exact_cover, greedy_cover
from services.apps.registry.scheduling.model import (
    Allocation,
    Plan,
    Provider,
    ProviderState,
    Request,
    Waiting,
)
from services.apps.registry.scheduling.qos import QosBook, QosRecord, parse_assessments
from services.apps.registry.scheduling.queue import DEFAULT_MAX_QUEUED, MAX_QUEUED_PER_CONSUMER, RequestQueue
from services.apps.registry.scheduling.scheduler import (
    DEFAULT_TOUT,
    DEFAULT_TR,
    MAX_ALLOCATIONS_PER_CONSUMER,
    MAX_COUNT,
    Scheduler,
)

__all__ = [
    "DEFAULT_MAX_QUEUED",
    "DEFAULT_QOS",
    "DEFAULT_TOUT",
    "DEFAULT_TR",
    "DEFAULT_WEIGHT",
    "EXACT_LIMIT",
    "MAX_ALLOCATIONS_PER_CONSUMER",
    "MAX_CAPABILITIES",
    "MAX_COUNT",
    "MAX_QUEUED_PER_CONSUMER",
    "Allocation",
    "Plan",
    "Provider",
    "ProviderState",
    "QosBook",
    "QosRecord",
    "Request",
    "RequestQueue",
    "Scheduler",
    "Waiting",
    "check_capabilities",
    "cover",
    "drive_distance",
    "exact_cover",
    "greedy_cover",
    "odometry_distance",
    "parse_assessments",
    "parse_capabilities",
    "rank_scores",
]
