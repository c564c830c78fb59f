"""GET /maps/{map}/stats and GET /health: the data gathered from the backend, combined by services.api.status."""

from __future__ import annotations

import asyncio
import time

from fastapi import APIRouter

from services.api import models
from services.api.registry import MapInfo
from services.api.routes.common import Api, ApiDep, MapName, errors, known_map
from services.api.status import WATCH_INTERVAL, health_report, map_stats
from services.process import get_logger

router = APIRouter()


def stats_now(api: Api, info: MapInfo) -> models.MapStats:
    """The map's stats as its shards answer now (they are asked; those that do not answer count as silent)."""
    backend = api.backend
    stats = backend.link.stats(info.name)
    latest = backend.robots.latest_seqs(vouched_only=True)  # stray poses make no lag (services.api.robots)
    now = time.monotonic()
    return map_stats(info, stats, latest, backend.link.rejects.snapshot(), now, backend.robots.vouched())


@router.get("/maps/{map}/stats", response_model=models.MapStats, tags=["status"], responses=errors(404, 422))
def get_stats(api: ApiDep, map: MapName) -> models.MapStats:
    """Per shard: liveliness, scans fused, messages received and rejected by key, lag behind SLAM."""
    return stats_now(api, known_map(api, map))


@router.get("/health", response_model=models.Health, tags=["status"])
def health(api: ApiDep) -> models.Health:
    """Shards alive and answering, scans fused and lag per map, the API's own rejected messages and what it
    refused at its limits. Degraded too while a robot's scans lag, its source is gone, a shard has counted
    scans of it and the shards have made no progress on them for STRANDED_AFTER s: they cannot come any more
    (a shard restarted after the source ended finds no history to take them from), and nothing else would say
    so. Only robots a process liveliness token vouched for have a lag (services.api.robots)."""
    backend = api.backend
    processes = list(backend.link.processes)  # a copy: Zenoh's threads change the set
    maps = {name: stats_now(api, known_map(api, name)) for name in backend.registry.names()}
    now = time.monotonic()
    return health_report(
        maps,
        processes,
        api.progress,
        now,
        uptime_s=now - backend.started,
        robots=backend.robots.robots(),
        rejected=backend.link.rejects.snapshot(),
        event_clients=backend.hub.clients,
        exports_running=api.export_slots.taken,
        refused=backend.link.refused.snapshot(),
        limits=api.limit_values(),
    )


async def watch(api: Api) -> None:
    """Look at every map every WATCH_INTERVAL s as /health does (its answer dropped), so that the API knows when a
    robot's scans stopped making progress before anyone asks (services.api.status). Runs until cancelled."""
    log = get_logger("api")
    while True:
        await asyncio.sleep(WATCH_INTERVAL)
        try:
            await asyncio.to_thread(health, api)
        except Exception:  # the watch must outlive any one look (logged, not swallowed)
            log.exception("looking at the maps' progress failed; trying again")
