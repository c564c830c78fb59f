"""The HTTP routes of `posegrid api`, one APIRouter per module, each over the application's
:class:`~services.api.routes.common.Api` (a FastAPI dependency: the backend, the limits, the slots):

- ``maps``: GET /maps and /maps/{map};
- ``tiles``: GET /maps/{map}/tiles/{z}/{x}/{y}.png and .npz;
- ``export``: GET /maps/{map}/export;
- ``status``: GET /maps/{map}/stats and /health (computed by services.api.status);
- ``robots``: GET /robots, /robots/{robot}/pose and /robots/{robot}/trajectory;
- ``events``: GET /events;
- ``common``: what they share (the dependency, error responses, map look-ups).

:data:`ROUTERS` is the order services.api.app includes them in (the order of the OpenAPI document's paths).
"""

from __future__ import annotations

from services.api.routes import events, export, maps, robots, status, tiles

ROUTERS = (maps.router, tiles.router, export.router, status.router, robots.router, events.router)
