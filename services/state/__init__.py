"""What a mapper shard and a SLAM node hold and decide, with no networking: the shard's grid and bookkeeping
(shard), the scan/pose join and the seq ledger (join), the SLAM steps in seq order (steps), tile ownership
(ownership) and the limits on what peers may send (limits). services.nodes wraps them in Zenoh processes."""
