"""The State Machine Service: SCXML charts whose actions are Sets, whose guards read properties.

* :class:`StateMachineService` — the service (catalog type ``statemachine``): ``machines``,
  ``M.definition``, ``M.start``, ``M.stop``, ``M.events``, ``M.state``, ``M.status``,
  ``M.variables``, ``M.log``, ``M.diagram``.
* :func:`compile_chart` — load and check a chart (SCXML, JSON or YAML); :class:`ChartError`
  names the line and what is wrong.
* :class:`Interpreter` — one run of a chart (the W3C SCXML algorithm).
* :class:`PropertyBinding` — Get, Set and Listen through a directory, each under a time limit.
* :func:`render_svg` — the chart as SVG with its active states marked.

The modules: ``expressions`` (the safe expression subset), ``document`` (SCXML, JSON and YAML
into one element tree, with lines), ``chart`` (the checked model), ``interpreter``,
``binding``, ``diagram``, ``service``; ``charts/`` holds charts shipped with the package.
"""

from services.apps.statemachine.binding import DEFAULT_ACTION_TIMEOUT, PropertyBinding
from services.apps.statemachine.chart import Chart, compile_chart
from services.apps.statemachine.diagram import render_svg
from services.apps.statemachine.document import ChartError
from services.apps.statemachine.interpreter import Interpreter
from services.apps.statemachine.service import Machine, StateMachineService, shipped_chart

__all__ = [
    "DEFAULT_ACTION_TIMEOUT",
    "Chart",
    "ChartError",
    "Interpreter",
    "Machine",
    "PropertyBinding",
    "StateMachineService",
    "compile_chart",
    "render_svg",
    "shipped_chart",
]
