"""Which mapper shard owns which map tile: rendezvous (highest-random-weight) hashing.

The owner of tile (tx, ty) among shards s_1..s_N is the shard with the largest score
blake2b("tx,ty|s"), a pure function of (tile, shard list) that every process and every machine computes
alike (Python's ``hash()`` is salted per process and would not be). Every tile has exactly one owner;
adding a shard moves only the tiles the new shard now wins, about 1/(N+1) of them, and moves each of
them to the new shard.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence


def tile_score(tile: tuple[int, int], shard: int | str) -> int:
    """The rendezvous score of ``shard`` for ``tile`` (tx, ty): an unsigned 64-bit integer."""
    key = f"{int(tile[0])},{int(tile[1])}|{shard}".encode()
    return int.from_bytes(hashlib.blake2b(key, digest_size=8).digest(), "big")


def tile_owner(tile: tuple[int, int], shards: Sequence[int | str]) -> int | str:
    """The shard of ``shards`` that owns ``tile``; ties (astronomically rare) go to the smaller id."""
    if not shards:
        raise ValueError("tile_owner needs at least one shard")
    return max(shards, key=lambda shard: (tile_score(tile, shard), _negated(shard)))


def _negated(shard: int | str):
    return -shard if isinstance(shard, int) else tuple(-ord(c) for c in shard)


def owns_tile(shard: int, shards: int) -> Callable[[int, int], bool]:
    """The predicate ``(tx, ty) -> bool`` for shard ``shard`` of shards 0 .. ``shards``-1 (cached)."""
    if not 0 <= shard < shards:
        raise ValueError(f"shard must be in 0 .. {shards - 1}, got {shard}")
    members = tuple(range(shards))
    cache: dict[tuple[int, int], bool] = {}

    def owns(tx: int, ty: int) -> bool:
        key = (tx, ty)
        if key not in cache:
            cache[key] = tile_owner(key, members) == shard
        return cache[key]

    return owns
