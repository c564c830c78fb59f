"""The parts the HTTP routes read, wired on one Zenoh session: the map registry, the tile service, the robot
tracker, the event hub and the link to the mapper shards. The routes receive it as a FastAPI dependency
(services.api.routes.common), so they can be built over any object with these attributes.
"""

from __future__ import annotations

import secrets
import time
from dataclasses import dataclass

import zenoh

from services.api.events import EventHub
from services.api.limits import MAX_MAPS, MAX_ROBOTS, STRAY_TTL, VERIFY_WINDOW
from services.api.mappers import MapperLink
from services.api.registry import MapRegistry
from services.api.robots import RobotTracker
from services.api.tiles import TileService


@dataclass
class Backend:
    """Everything the routes use; ``started`` is the time.monotonic() the API started, s."""

    registry: MapRegistry
    tiles: TileService
    robots: RobotTracker
    hub: EventHub
    link: MapperLink
    started: float

    @classmethod
    def open(
        cls,
        session: zenoh.Session,
        cache_bytes: int,
        query_timeout: float,
        max_maps: int = MAX_MAPS,
        max_robots: int = MAX_ROBOTS,
        stray_ttl: float = STRAY_TTL,
        verify_window: float = VERIFY_WINDOW,
    ) -> Backend:
        """Wire the parts on an open Zenoh session and start listening (limits: services.api.registry,
        services.api.robots, services.api.mappers; cache_bytes in bytes; query_timeout, stray_ttl and
        verify_window in s)."""
        epoch = secrets.token_hex(4)
        registry = MapRegistry(max_maps)
        robots, hub = RobotTracker(max_robots=max_robots, stray_ttl=stray_ttl), EventHub(epoch)
        link = MapperLink(session, registry, robots, hub, query_timeout, verify_window)
        tiles = TileService(registry, link, epoch, cache_bytes, on_change=hub.tile_changed)
        link.start()
        return cls(registry, tiles, robots, hub, link, time.monotonic())

    def close(self) -> None:
        """Stop listening (the Zenoh session stays open: its owner closes it)."""
        self.link.close()
