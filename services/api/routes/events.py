"""GET /events: the server-sent event stream of tile changes and poses (services.api.events), at most
--max-event-clients at once."""

from __future__ import annotations

from contextvars import ContextVar

from fastapi import APIRouter
from fastapi.responses import StreamingResponse

from services.api.limits import Slots
from services.api.routes.common import ApiDep, busy, error_response

router = APIRouter()


class ClientGone(Exception):
    """The server could not write the stream's next event: its client has gone."""


#: set in a request's context when its event stream ended because its client had gone (:class:`SlotStream`): the
#: server then says "ASGI callable returned without completing response" of it, which is no error of the API's
#: (services.api.server.QuietGoneClients drops that line)
CLIENT_GONE: ContextVar[bool] = ContextVar("client_gone", default=False)


class SlotStream(StreamingResponse):
    """A streaming response that gives its slot back and closes its events' generator when it ends, however it
    ends (a client gone before the first event included).

    A client that leaves with another request queued behind the stream on its connection is not seen to go (the
    server reads no more of that connection while the stream runs): the stream's next write (an event or the
    keep-alive) raises RuntimeError from the closed transport (uvloop's), which is that client gone, not an error of
    the API's. Ended by it, Starlette leaves the generator suspended, and with it its event-hub client, until the
    garbage collector (a probe counted 39 such clients after 140 streams, with a queue each), so it is closed
    here."""

    def __init__(self, content, slots: Slots, **kwargs) -> None:
        super().__init__(content, **kwargs)
        self.slots = slots

    async def __call__(self, scope, receive, send) -> None:
        async def send_or_gone(message) -> None:
            try:
                await send(message)
            except RuntimeError as exc:
                raise ClientGone from exc

        try:
            await super().__call__(scope, receive, send_or_gone)
        except ClientGone:
            CLIENT_GONE.set(True)  # nothing to answer, no one to answer it to
        finally:
            close = getattr(self.body_iterator, "aclose", None)
            if close is not None:
                await close()
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
