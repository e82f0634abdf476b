"""The HMI's line page: ``GET /line`` (static/line.html) and ``GET /api/line`` (JSON), from the
coordinator's ``line/query_losses`` and ``line/query_episodes`` services.

``/api/line?shift=current|previous|<YYYY-MM-DD name>`` answers ``{cell, shift, shifts, trend,
episodes, episodes_total, current}``: the losses of the shift (``packml_ros2.line_msgs`` dicts;
the lifetime when the cell has no shift calendar), the last shifts (for the waterfall's choice),
the OEE trend (16 windows of 15 min), the episodes of the shift (newest first, at most 200) and
the open episode. Reading needs no token, like the other screens.
"""

from __future__ import annotations

import asyncio
import re
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import FileResponse

from .. import line_msgs
from ..client import call_future
from ..core.reasons import Reason
from .access import Refusal
from .guard import Json, refuse

TIMEOUT = 5.0
SHIFT = re.compile(r"^(current|previous|\d{4}-\d{2}-\d{2} [A-Za-z_][A-Za-z0-9_]{0,60})$")
TREND_STEP = 900.0
TREND_COUNT = 16
SHIFTS_SHOWN = 6
EPISODES = 200


class LineApi:
    """The coordinator's line services, called from the web server's event loop."""

    def __init__(self, bridge: Any) -> None:
        from packml_interfaces.srv import QueryEpisodes, QueryLosses

        self.bridge = bridge
        self.cell = bridge.cell.cell
        base = f"/{self.cell}/coordinator/line"
        self.QueryEpisodes, self.QueryLosses = QueryEpisodes, QueryLosses
        self.losses = bridge.node.create_client(QueryLosses, f"{base}/query_losses")
        self.episodes = bridge.node.create_client(QueryEpisodes, f"{base}/query_episodes")
        self.base = base

    async def _call(self, client: Any, request: Any, name: str) -> Any:
        future = call_future(client, request, f"{self.base}/{name}")
        return await asyncio.wait_for(asyncio.wrap_future(future), TIMEOUT)

    async def _losses(self, **fields: Any) -> Any:
        return await self._call(self.losses, self.QueryLosses.Request(**fields), "query_losses")

    async def collect(self, shift: str) -> dict[str, Any]:
        window = "shift" if shift == "current" else f"shift:{shift}"
        chosen = await self._losses(window=window)
        if not chosen.accepted and shift == "current":
            chosen = await self._losses(window="lifetime")  # no shift calendar
        if not chosen.accepted:
            raise LookupError(chosen.message)
        w = chosen.windows[0]
        in_shift = self.QueryEpisodes.Request(since=w.start, until=w.end, limit=EPISODES)
        open_now = self.QueryEpisodes.Request(open_only=True, limit=1)
        shifts, trend, eps, current = await asyncio.gather(
            self._losses(window="shifts", count=SHIFTS_SHOWN),
            self._losses(window="trend", step=TREND_STEP, count=TREND_COUNT),
            self._call(self.episodes, in_shift, "query_episodes"),
            self._call(self.episodes, open_now, "query_episodes"),
        )
        return {
            "cell": self.cell,
            "shift": line_msgs.losses_dict(w),
            "shifts": [line_msgs.losses_dict(x) for x in shifts.windows],
            "trend": [line_msgs.losses_dict(x) for x in trend.windows],
            "episodes": [line_msgs.episode_dict(e) for e in eps.episodes],
            "episodes_total": eps.total,
            "current": line_msgs.episode_dict(current.episodes[0]) if current.episodes else None,
        }


def add_routes(app: FastAPI, bridge: Any, static: Any) -> None:
    """``GET /line`` and ``GET /api/line`` on ``app``."""
    api = LineApi(bridge)

    @app.get("/line", include_in_schema=False)
    async def line_page() -> FileResponse:
        return FileResponse(static / "line.html", media_type="text/html")

    @app.get("/api/line")
    async def line_data(request: Request, shift: str = "current") -> Json:
        if len(shift) > 80 or not SHIFT.match(shift):
            return refuse(
                Refusal(
                    400,
                    Reason.INVALID_ARGUMENT,
                    "BAD_ARGUMENT",
                    "shift is current, previous or 'YYYY-MM-DD name'",
                )
            )
        try:
            return Json(await api.collect(shift))
        except LookupError as exc:
            return refuse(Refusal(404, Reason.INVALID_ARGUMENT, "NOT_FOUND", str(exc)))
        except (TimeoutError, Exception) as exc:  # the coordinator is not there (or not answering)
            return refuse(
                Refusal(
                    503,
                    Reason.UNIT_UNAVAILABLE,
                    "UNAVAILABLE",
                    f"the coordinator of {api.cell} does not answer ({type(exc).__name__})",
                )
            )
