"""v2i.core.scheduler.Timeline: due order, then rank, then push order."""

import random

import pytest

from v2i.core.scheduler import Timeline


def drained(timeline: Timeline) -> list:
    out = []
    while timeline:
        out.append(timeline.pop())
    return out


def test_events_come_out_by_due_time_then_rank_then_push_order():
    timeline = Timeline()
    timeline.push(20, "late")
    timeline.push(10, "b", rank=1)
    timeline.push(10, "a", rank=1)
    timeline.push(10, "first", rank=0)
    assert len(timeline) == 4 and timeline.head() == (10, "first")
    assert drained(timeline) == [(10, "first"), (10, "b"), (10, "a"), (20, "late")]
    assert not timeline


def test_events_are_never_compared():
    """Unorderable events (callables, dicts) at one time and rank: push order decides."""
    timeline = Timeline()
    events = [{"k": k} for k in range(50)]
    for event in events:
        timeline.push(5, event)
    assert [event for _, event in drained(timeline)] == events


def test_the_order_is_a_stable_sort_of_due_and_rank():
    rng = random.Random(0)
    pushed = [(rng.randrange(10), rng.randrange(3), k) for k in range(500)]
    timeline = Timeline()
    for due_ns, rank, k in pushed:
        timeline.push(due_ns, k, rank)
    expected = [(due_ns, k) for due_ns, rank, k in sorted(pushed, key=lambda e: (e[0], e[1]))]
    assert drained(timeline) == expected


def test_pushing_while_draining_keeps_the_order_and_clear_counts():
    timeline = Timeline()
    timeline.push(1, "a")
    due_ns, _ = timeline.pop()
    timeline.push(due_ns, "same time, pushed later")
    timeline.push(0, "earlier")
    assert [event for _, event in drained(timeline)] == ["earlier", "same time, pushed later"]
    timeline.push(3, "x")
    timeline.push(4, "y")
    assert timeline.clear() == 2 and not timeline
    with pytest.raises(IndexError):
        timeline.head()
