"""Reading a sharded map over Zenoh: the shards' stats, their tiles, and the map assembled from them.

Used by the launcher (progress, export), the source (flow control), the API and the benchmark. Replies that do
not decode are skipped and counted in :attr:`MapReader.rejected`, never trusted.

Who answers (:func:`sort_answers`): any peer may declare a queryable on a shard's keys, so a reply is taken for a
shard only when the shard's liveliness token is up, and each reply is known by the Zenoh session that sent it
(zenoh sets a reply's ``replier_id``; a peer cannot give another session's). A round in which two sessions answer
as one shard, or the shards disagree on their count, is not trusted: the reader says why
(:attr:`ShardAnswers.problems`) and goes on as if no shard had answered, rather than act on forged counts. A tile is
taken only from the session whose stats answered for the shard that owns it by the ownership rule
(services.state.ownership). Without access control a peer that declares a shard's token *and* answers for it
while the real shard is down is that shard as far as anyone can tell (docs/security.md).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable
from dataclasses import dataclass, field

import zenoh

from mapping.grid import TiledGrid
from schemas.messages import MessageError, ShardStats, TileUpdate, decode_message
from schemas.wire import NAME_RULE, is_valid_name
from services import keys
from services.errors import UsageError
from services.state.ownership import owns_tile
from services.zenoh_config import replier


class IncompleteMap(RuntimeError):
    """The tiles received do not add up to what the shards say they hold."""


@dataclass(frozen=True)
class ShardAnswers:
    """One round of a map's shards' stats (:func:`sort_answers`): ``stats`` and ``answerers`` (the Zenoh session id
    whose stats were kept) by shard index, of the shards whose token is up; ``duplicated``: the shards two sessions
    answered for; ``problems``: why the round cannot be trusted (two sessions answering as one shard, shards
    disagreeing on their count), empty when it can; ``left_out``: (key, kind, why) of each reply not taken, kind
    "key" (its key or map is not its stats') or "unverified" (no liveliness token is up for its shard)."""

    stats: dict[int, ShardStats] = field(default_factory=dict)
    answerers: dict[int, str] = field(default_factory=dict)
    duplicated: frozenset[int] = frozenset()
    problems: list[str] = field(default_factory=list)
    left_out: list[tuple[str, str, str]] = field(default_factory=list)

    @property
    def trusted(self) -> dict[int, ShardStats]:
        """The stats when the round can be trusted, else none (as if no shard had answered)."""
        return {} if self.problems else self.stats

    @property
    def untokened(self) -> int:
        """Replies left out for a shard with no liveliness token up."""
        return sum(kind == "unverified" for _, kind, _ in self.left_out)


def sort_answers(
    map_name: str, replies: Iterable[tuple[str, str, ShardStats]], tokens: Collection[int]
) -> ShardAnswers:
    """The stats replies (key, sender's session id, stats) of map ``map_name``'s shards, sorted (module docstring):
    only shards in ``tokens`` (the shard indices whose liveliness token is up) are kept; of a shard that two
    sessions answer for, the stats of the one up longer."""
    stats: dict[int, ShardStats] = {}
    answerers: dict[int, str] = {}
    senders: dict[int, set[str]] = {}
    left_out: list[tuple[str, str, str]] = []
    for key, sender, message in replies:
        if message.map != map_name or key != keys.stats_key(map_name, message.shard):
            left_out.append((key, "key", f"stats of shard {message.shard} of map {message.map!r} on {key}"))
        elif message.shard not in tokens:
            left_out.append((key, "unverified", f"stats of shard {message.shard}, whose token is not up"))
        else:
            senders.setdefault(message.shard, set()).add(sender)
            if message.shard not in stats or message.uptime > stats[message.shard].uptime:
                stats[message.shard], answerers[message.shard] = message, sender
    duplicated = frozenset(shard for shard, sessions in senders.items() if len(sessions) > 1)
    problems = [
        f"{len(senders[shard])} processes answer as shard {shard} of map {map_name!r} (a shard started twice, or a "
        "peer forging its stats: docs/security.md)"
        for shard in sorted(duplicated)
    ]
    counts = sorted({s.shards for s in stats.values()})
    if len(counts) > 1:
        problems.append(
            f"the shards of map {map_name!r} disagree on their count ({', '.join(map(str, counts))}: shards of two "
            "runs, or a peer forging stats: docs/security.md)"
        )
    return ShardAnswers(stats, answerers, duplicated, problems, left_out)


def _check_timeout(timeout: float) -> None:
    """UsageError unless ``timeout`` (s) is a finite number >= 0 (NaN or inf: zenoh's "negative timeout")."""
    if not (math.isfinite(timeout) and timeout >= 0):  # (also NaN)
        raise UsageError(f"a timeout must be a finite number of seconds >= 0, got {timeout!r}")


class MapReader:
    """Queries the shards of map ``map_name`` on an open session."""

    def __init__(self, session: zenoh.Session, map_name: str):
        """UsageError for a map name no key may hold (NAME_RULE): "*" or "a?b" made a query of other keys, or of
        every map, and "main/" raised zenoh's own error, which quotes its Rust sources."""
        if not is_valid_name(map_name):
            raise UsageError(f"the map name {map_name!r} is not valid ({NAME_RULE})")
        self.session = session
        self.map_name = map_name
        self.rejected = 0

    def _replies(self, selector: str, expected, timeout: float) -> list:
        """(key, sender's session id, message) of each reply that decodes as ``expected``."""
        _check_timeout(timeout)
        messages = []
        handler = self.session.get(
            selector,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
            congestion_control=zenoh.CongestionControl.BLOCK,
            timeout=timeout,
        )
        for reply in handler:
            if reply.ok is None:
                self.rejected += 1
                continue
            try:
                message = decode_message(reply.ok.payload.to_bytes(), expected)
            except MessageError:
                self.rejected += 1
                continue
            messages.append((str(reply.ok.key_expr), replier(reply), message))
        return messages

    def tokens(self, timeout: float = 5.0) -> set[int]:
        """The shard indices of the map whose liveliness token is up."""
        return self._tokens(self._ask_tokens(timeout))

    def shards_up(self, shards: int, timeout: float = 2.0) -> int:
        """How many of shards 0 .. ``shards``-1 of the map (its shard count: the launcher's) have their liveliness
        token up: distinct indices, each in its one decimal form (a peer's token on alive/00, or on alive/5 of a map
        of 2 shards, counts for none; a count of the replies let a source start with no shard up). A process that
        knows only how many shards to wait for counts :meth:`tokens`."""
        return sum(index < shards for index in self.tokens(timeout))

    def _ask_tokens(self, timeout: float):
        _check_timeout(timeout)
        return self.session.liveliness().get(keys.shard_alive_key(self.map_name, "*"), timeout=timeout)

    def _tokens(self, handler) -> set[int]:
        """The shard indices of the tokens a liveliness query's ``handler`` gives (iterating it waits)."""
        up = set()
        for reply in handler:
            parsed = keys.parse_shard_alive_key(str(reply.ok.key_expr)) if reply.ok is not None else None
            if parsed is not None and parsed[0] == self.map_name:
                up.add(parsed[1])
        return up

    def answers(self, timeout: float = 5.0, tokens: Collection[int] | None = None) -> ShardAnswers:
        """One round of the shards' stats, sorted (:func:`sort_answers`) against ``tokens`` (the shards whose
        liveliness token is up; None: asked now, alongside the stats, within the same ``timeout`` s); what is left
        out is counted in :attr:`rejected`."""
        asked = None if tokens is not None else self._ask_tokens(timeout)
        replies = self._replies(keys.stats_key(self.map_name, "*"), ShardStats, timeout)
        answers = sort_answers(self.map_name, replies, self._tokens(asked) if tokens is None else tokens)
        self.rejected += len(answers.left_out)
        return answers

    def stats(self, timeout: float = 5.0) -> dict[int, ShardStats]:
        """Every reachable shard's stats, by shard index, when the round can be trusted (else none:
        :meth:`answers` says why)."""
        return self.answers(timeout).trusted

    def tiles(self, timeout: float = 60.0) -> list[TileUpdate]:
        """Every tile of zoom level 0 from every shard (whole tiles), whoever sent it."""
        return [t for _, _, t in self._tiles(timeout)]

    def _tiles(self, timeout: float) -> list[tuple[str, str, TileUpdate]]:
        replies = self._replies(keys.tile_key(self.map_name, 0, "*", "*"), TileUpdate, timeout)
        return [(key, sender, t) for key, sender, t in replies if t.map == self.map_name]

    def assemble(
        self, shards: int, resolution: float, timeout: float = 60.0, tokens: Collection[int] | None = None
    ) -> TiledGrid:
        """The whole map as one grid of cells ``resolution`` m, checked against the shards' own tile counts; its
        stats sorted against ``tokens`` (:meth:`answers`).

        Raises :class:`IncompleteMap` when a shard does not answer or says the map has another number of shards, or a
        tile is missing (fewer of a shard's arrive than its stats held; more may, made since) or duplicated.
        """
        answers = self.answers(tokens=tokens)
        if answers.problems:
            raise IncompleteMap(answers.problems[0])
        stats = answers.stats
        if sorted(stats) != list(range(shards)):
            raise IncompleteMap(f"expected shards 0..{shards - 1} of map {self.map_name!r}, got {sorted(stats)}")
        for shard, shard_stats in stats.items():
            if shard_stats.shards != shards:
                raise IncompleteMap(
                    f"shard {shard} says map {self.map_name!r} has {shard_stats.shards} shard(s), not {shards}"
                )
        tiles = self._owners_tiles(self._tiles(timeout), answers.answerers, shards)
        per_shard = dict.fromkeys(range(shards), 0)
        seen = set()
        for tile in tiles:
            if (tile.tx, tile.ty) in seen:
                raise IncompleteMap(f"tile ({tile.tx}, {tile.ty}) came from two shards")
            seen.add((tile.tx, tile.ty))
            per_shard[tile.shard] = per_shard.get(tile.shard, 0) + 1
        for shard, count in per_shard.items():  # (asked after the stats: a shard may have made tiles meanwhile)
            owned = stats[shard].tiles_owned if shard in stats else 0
            if count < owned:
                raise IncompleteMap(f"shard {shard} holds {owned} tiles but {count} arrived")
        if not tiles:
            return TiledGrid(resolution)
        grid = TiledGrid(resolution, tiles[0].tile_size)
        for tile in tiles:
            if tile.resolution != resolution:
                raise IncompleteMap(
                    f"the shards map at {tile.resolution} m (tile {tile.tx}, {tile.ty}), not {resolution} m"
                )
            if tile.z != 0 or not tile.is_whole() or tile.tile_size != grid.tile_size:
                raise IncompleteMap(
                    f"tile ({tile.tx}, {tile.ty}) arrived as a partial window or at zoom level {tile.z}"
                )
            grid.set_tile((tile.tx, tile.ty), *tile.whole_layers())
        return grid

    def _owners_tiles(
        self, replies: list[tuple[str, str, TileUpdate]], answerers: dict[int, str], shards: int
    ) -> list[TileUpdate]:
        """The tiles that their owner sent: the shard the ownership rule gives the tile, from the session that
        answered for that shard's stats; the others are counted in :attr:`rejected` (a peer answering the tile
        query with tiles of its own)."""
        owned = [
            tile
            for key, sender, tile in replies
            if 0 <= tile.shard < shards
            and key == keys.tile_key(self.map_name, 0, tile.tx, tile.ty)
            and answerers.get(tile.shard) == sender
            and owns_tile(tile.shard, shards)(tile.tx, tile.ty)
        ]
        self.rejected += len(replies) - len(owned)
        return owned
