"""What a process remembers within a byte budget (`ground.remembered`)."""

from ground.remembered import Remembered


def test_that_the_least_recently_used_go_first_when_the_budget_is_exceeded_but_never_the_newest():
    r = Remembered(max_bytes=10, nbytes=len)
    r.put("a", "xxxx")
    r.put("b", "yyyy")
    assert r.get("a") == "xxxx"  # now the most recently used
    r.put("c", "zzzz")  # 12 bytes: b, the least recently used, goes
    assert r.get("b") is None and r.get("a") == "xxxx" and r.get("c") == "zzzz"
    r.put("d", "w" * 40)  # alone over the budget: kept, the rest let go
    assert r.get("d") == "w" * 40 and r.get("a") is None and r.get("c") is None
    r.clear()
    assert r.get("d") is None


def test_that_a_value_the_caller_cannot_use_is_not_returned():
    r = Remembered(max_bytes=100, nbytes=len)
    r.put("k", "short")
    assert r.get("k", lambda v: len(v) > 10) is None and r.get("k", lambda v: len(v) > 3) == "short"
