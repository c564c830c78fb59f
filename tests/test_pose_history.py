"""A SLAM node's kept poses (services.state.pose_history): bounded by bytes, oldest first out, and read by the
node's queryable while its thread keeps more."""

from __future__ import annotations

import threading

from services.state.pose_history import PoseHistory


def test_the_oldest_poses_go_first_past_the_byte_bound_and_a_pose_published_again_moves_to_the_end():
    kept = PoseHistory(max_bytes=10)
    for seq, payload in ((0, b"aaaa"), (1, b"bbbb"), (2, b"cc")):  # 10 bytes: all kept
        kept.keep(seq, payload)
    assert kept.poses(lambda seq: True) == [b"aaaa", b"bbbb", b"cc"]
    kept.keep(3, b"d")  # 11 bytes: seq 0 goes
    assert kept.poses(lambda seq: True) == [b"bbbb", b"cc", b"d"]
    kept.keep(1, b"B")  # published again (a restarted node): replaced, and now the newest
    assert kept.poses(lambda seq: True) == [b"cc", b"d", b"B"]
    assert kept.poses(lambda seq: seq >= 2 and seq != 3) == [b"cc"]


def test_a_reader_sees_the_poses_in_order_while_another_thread_keeps_them():
    kept = PoseHistory(max_bytes=1 << 20)
    done = threading.Event()
    reads: list[list[bytes]] = []
    errors: list[Exception] = []

    def read() -> None:
        try:
            while not done.is_set():
                reads.append(kept.poses(lambda seq: True))
        except Exception as exc:  # (an OrderedDict changed while it is walked: RuntimeError)
            errors.append(exc)

    reader = threading.Thread(target=read)
    reader.start()
    for seq in range(20_000):
        kept.keep(seq, seq.to_bytes(4, "big"))
    done.set()
    reader.join(30)
    assert (
        errors == []
        and reads
        and all([int.from_bytes(p, "big") for p in read] == list(range(len(read))) for read in reads)
    )  # each read: the poses kept so far, in order
    assert len(kept.poses(lambda seq: True)) == 20_000
