"""The hot path's per-bank memo: made once, evicted least-recently-used, never another owner's value."""

from __future__ import annotations

from service.vision.memo import Memo


class Owner:
    pass


def test_made_once_per_owner_and_key_and_evicted_least_recently_used():
    memo, calls = Memo(2), []

    def make(tag):
        return lambda: calls.append(tag) or tag

    a, b, c = Owner(), Owner(), Owner()
    assert memo.get(a, 1, make("a1")) == "a1" and memo.get(a, 1, make("again")) == "a1"
    assert memo.get(a, 2, make("a2")) == "a2"
    assert memo.get(a, 1, make("again")) == "a1"  # now the most recent
    assert memo.get(b, 1, make("b1")) == "b1"  # evicts (a, 2)
    assert memo.get(a, 2, make("a2 remade")) == "a2 remade"
    assert memo.get(c, 1, make("c1")) == "c1"
    assert calls == ["a1", "a2", "b1", "a2 remade", "c1"]


def test_a_recycled_id_does_not_return_the_old_owners_value():
    memo = Memo(4)
    first = Owner()
    memo.get(first, "k", lambda: "first's")
    stale = (id(first), "k")
    impostor = Owner()
    memo._items[(id(impostor), "k")] = memo._items.pop(stale)  # as if impostor had been given first's id
    assert memo.get(impostor, "k", lambda: "impostor's") == "impostor's"


def test_clear_forgets_every_value():
    memo, a = Memo(4), Owner()
    memo.get(a, 1, lambda: "old")
    memo.clear()
    assert memo.peek(a, 1) is None and memo.get(a, 1, lambda: "new") == "new"
