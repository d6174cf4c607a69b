"""experiments.bench.epoch_profile: its option checks; experiments.bench.tracing: the trace summary (a synthetic
trace)."""

import pytest

from experiments.bench import epoch_profile as bench_profile
from experiments.bench import tracing


def test_summarise_groups_by_stream_counts_events_and_ranks_operations():
    events = [
        {"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/device:GPU:0"}},
        {"ph": "M", "name": "thread_name", "pid": 1, "tid": 7, "args": {"name": "Stream #14(Compute)"}},
        {"ph": "X", "pid": 1, "tid": 7, "name": "fusion_a", "dur": 3.0},
        {"ph": "X", "pid": 1, "tid": 7, "name": "fusion_b", "dur": 5.0},
        {"ph": "X", "pid": 1, "tid": 7, "name": "fusion_a", "dur": 4.0},
        {"ph": "X", "pid": 2, "tid": 1, "name": "host_op", "dur": 1.0},  # no names: ids stand in
        {"ph": "i", "pid": 1, "tid": 7, "name": "instant"},  # not a complete event
    ]
    rows = tracing.summarise(events, top=1)
    assert [(r["process"], r["thread"], r["events"]) for r in rows] == [
        ("/device:GPU:0", "Stream #14(Compute)", 3),
        ("2", "1", 1),
    ]
    assert rows[0]["seconds"] == pytest.approx(12e-6)
    assert rows[0]["top"] == [("fusion_a", pytest.approx(7e-6))]


def test_bad_seed_count_is_a_one_line_error():
    with pytest.raises(SystemExit, match="--seeds 0: must be a positive integer"):
        bench_profile.main(["--seeds", "0"])
