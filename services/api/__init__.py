"""`posegrid api`: the HTTP API and the browser viewer, a Zenoh client of the mapper shards (docs/api.md).

Modules, one job each:
- ``registry``: what the API knows about each map (shards alive, level-0 tiles and their versions),
- ``mappers``: the Zenoh side: subscriptions (tile updates, poses, liveliness) and queries to the shards,
- ``tiles``: tiles at every zoom level, fetched from the shards, combined (mapping.pyramid), cached,
- ``render``: a tile's layers, or an exported map's, as PNG, .npz or zipped PGM bytes,
- ``robots``: the latest pose distribution and the trajectory of each robot,
- ``events``: the server-sent event stream of tile changes and poses,
- ``models``: the JSON response schemas (the OpenAPI document derives from them),
- ``backend``: those parts wired on one Zenoh session, what the routes are built over,
- ``routes``: the FastAPI routers, one module per group of routes (maps, tiles, export, status, robots, events),
- ``status``: shard statistics and health from plain data (what /maps/{map}/stats and /health say),
- ``app``: the FastAPI application (routers, viewer, error handlers); ``fastpath``: answers repeated tile
  requests from the cache before it,
- ``export``: the raster size of an export, known before it is built, and the window that crops one,
- ``limits``: what the API holds and runs at most, and the counts of what it refused at those limits,
- ``guard``: the Host header and access-token checks in front of everything,
- ``protocol``: uvicorn's HTTP protocol with a deadline for each request to arrive,
- ``server``: runs it all under uvicorn; ``static/``: the viewer (one HTML, one JS, one CSS file).
"""
