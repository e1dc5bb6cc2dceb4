"""fusion.identity_memo: one computation per object (by identity, not equality), afresh past capacity."""

from collections import Counter

from fusion.identity_memo import IdentityMemo


def test_one_computation_per_object_matched_by_identity():
    calls = Counter()

    def listed(x):
        calls[id(x)] += 1
        return [x]

    memo = IdentityMemo(listed, capacity=4)
    a, equal_to_a = [1, 2], [1, 2]
    assert memo(a)[0] is a and memo(a)[0] is a and calls[id(a)] == 1
    assert memo(equal_to_a)[0] is equal_to_a and calls[id(equal_to_a)] == 1  # equal, not the same: its own entry


def test_past_capacity_the_memo_starts_afresh():
    calls = Counter()
    memo = IdentityMemo(lambda x: calls.update([id(x)]), capacity=2)
    a, b, c = object(), object(), object()
    memo(a), memo(b), memo(a)
    assert calls[id(a)] == 1
    memo(c)  # the third object: the two kept are forgotten
    memo(a)
    assert calls[id(a)] == 2 and calls[id(b)] == 1 and calls[id(c)] == 1
