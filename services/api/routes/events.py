"""GET /events: the server-sent event stream of tile changes and poses (services.api.events), at most
--max-event-clients at once."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import StreamingResponse

from services.api.limits import Slots
from services.api.routes.common import ApiDep, busy, error_response

router = APIRouter()


class SlotStream(StreamingResponse):
    """A streaming response that gives its slot back when it ends, however it ends (a client gone before the
    first event included)."""

    def __init__(self, content, slots: Slots, **kwargs) -> None:
        super().__init__(content, **kwargs)
        self.slots = slots

    async def __call__(self, scope, receive, send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self.slots.give_back()


@router.get(
    "/events",
    tags=["status"],
    response_class=StreamingResponse,
    responses={
        200: {
            "description": "server-sent events: hello, tiles ({map, tiles: [[tx, ty, version], ...]}, level-0 "
            "tiles that changed), pose ({robot, seq, stamp, mean, covariance, samples, weights}), resync",
            "content": {"text/event-stream": {}},
        },
        503: error_response(503, "every event-stream slot is taken (--max-event-clients); retry after Retry-After s"),
    },
)
async def events(api: ApiDep) -> StreamingResponse:
    """A stream of tile-changed and pose events, batched every 0.25 s (docs/api.md); at most
    --max-event-clients at once."""
    if not api.event_slots.take():  # on the event loop: no other request takes a slot between check and take
        api.backend.link.refused.add("event_clients")
        raise busy("event streams", api.limits.event_clients, "--max-event-clients")
    return SlotStream(
        api.backend.hub.stream(),
        api.event_slots,
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
