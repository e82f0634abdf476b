"""The operator HMI in the browser (``packml hmi <cell.yaml>``; docs/packml.md §8).

- :mod:`.settings`: the ``hmi:`` block of the cell file (host, port, token, title), validated;
- :mod:`.bridge`: the ROS side: a node that follows the cell's units and coordinator, turns their
  messages into JSON-able dicts, pushes change events to listeners and calls the units' services
  with source ``hmi``;
- :mod:`.server`: the web side (FastAPI on uvicorn): the page and its assets (all served locally),
  a server-sent-events stream of the cell's state, and POST actions guarded by the optional token.
"""

from .settings import DEFAULT_HOST, DEFAULT_PORT, HmiSettings, hmi_settings

__all__ = ["DEFAULT_HOST", "DEFAULT_PORT", "HmiSettings", "hmi_settings"]
