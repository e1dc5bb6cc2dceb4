"""v2i.core.identity_memo: one computation per object (by identity, not equality), the first entry forgotten past capacity."""

from collections import Counter

from v2i.core.identity_memo import IdentityMemo


def test_one_computation_per_object_matched_by_identity():
    calls = Counter()

    def listed(x):
        calls[id(x)] += 1
        return [x]

    memo = IdentityMemo(listed, capacity=4)
    a, equal_to_a = [1, 2], [1, 2]
    assert memo(a)[0] is a and memo(a)[0] is a and calls[id(a)] == 1
    assert memo(equal_to_a)[0] is equal_to_a and calls[id(equal_to_a)] == 1  # equal, not the same: its own entry


def test_past_capacity_the_memo_forgets_its_first_entry():
    calls = Counter()
    memo = IdentityMemo(lambda x: calls.update([id(x)]), capacity=2)
    a, b, c = object(), object(), object()
    memo(a), memo(b), memo(a)
    assert calls[id(a)] == 1
    memo(c)  # the third object: a, the first entry made, is forgotten; b is kept
    memo(b)
    assert calls[id(b)] == 1 and calls[id(c)] == 1
    memo(a)  # computed again (and b, now the first entry, forgotten)
    memo(c)
    assert calls[id(a)] == 2 and calls[id(c)] == 1
    memo(b)
    assert calls[id(b)] == 2 and len(memo._kept) == 2
