"""services.heap: frozen objects are skipped by collections until reclaimed."""

import gc
import weakref

from services.heap import freeze_heap, reclaim_heap


class Node:
    pass


def cycle() -> weakref.ref:
    a, b = Node(), Node()
    a.other, b.other = b, a
    return weakref.ref(a), (a, b)


def test_a_cycle_alive_at_the_freeze_waits_for_reclaim():
    gc.collect()
    try:
        ref, pair = cycle()
        freeze_heap()
        assert gc.get_freeze_count() > 0
        del pair  # garbage now, but frozen: a collection does not walk it
        gc.collect()
        assert ref() is not None
        young, young_pair = cycle()  # created after the freeze: collected as usual
        del young_pair
        gc.collect()
        assert young() is None
        assert reclaim_heap() >= 2
        assert ref() is None
        assert gc.get_freeze_count() > 0  # what survived is frozen again
    finally:
        gc.unfreeze()
