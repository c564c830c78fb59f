"""A mapper shard's durable state (docs/persistence.md): its SQLite store (db), what it changed since its last
commit (journal), the thread that commits (writer) and a `posegrid run`'s state directory (run)."""
