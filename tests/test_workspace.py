"""The Workspace: one working array kept from call to call (the imager's voltage layout, the tree's working
rows), used again only when nothing still reads it."""
import gc

import numpy as np

from bf_epic_blocks.imaging._xp import Workspace


def test_an_array_is_the_last_one_s_memory_once_its_lease_is_gone():
    w = Workspace()
    a, lease = w.take(np, (3, 5), np.float32)
    a[:] = 7
    ptr = a.ctypes.data
    del lease
    b, lease = w.take(np, (2, 5), np.float16)            # smaller, another dtype: the same bytes
    assert b.ctypes.data == ptr and b.shape == (2, 5) and b.dtype == np.float16 and b.flags.c_contiguous
    assert w.nbytes == 60


def test_an_array_still_read_is_not_overwritten():
    """While a reader holds the lease (a search's staged rows), the next call makes a new array and the
    held one keeps its values."""
    w = Workspace()
    a, lease = w.take(np, (4,), np.int64)
    a[:] = [1, 2, 3, 4]
    b, lease2 = w.take(np, (4,), np.int64)
    assert b.ctypes.data != a.ctypes.data
    b[:] = -1
    assert list(a) == [1, 2, 3, 4]
    del lease, lease2
    gc.collect()
    c, _ = w.take(np, (4,), np.int64)                   # the newest is the one kept
    assert c.ctypes.data == b.ctypes.data


def test_a_larger_array_makes_a_larger_buffer_that_smaller_ones_then_share():
    w = Workspace()
    w.take(np, (10,), np.uint8)
    big, lease = w.take(np, (100,), np.uint8)
    assert w.nbytes == 100
    del lease
    small, lease = w.take(np, (10,), np.uint8)
    assert small.ctypes.data == big.ctypes.data and w.nbytes == 100
    w.release()
    assert w.nbytes == 0
    z, _ = w.take(np, (0, 3), np.float32)               # an empty array is an array too
    assert z.shape == (0, 3)



def test_two_buffers_take_turns_while_a_reader_holds_the_last_call_s(monkeypatch):
    """depth=2 (a search that reads a push's rows during the next push): with the previous call's array
    still read at each call, the two buffers alternate and no third is made -- with one buffer, each call
    made a new array (a 2.9 GB one, each push of the station's search, until a pool under its limit had
    no block of that size)."""
    made, empty = [], np.empty

    def counted(*args, **kw):
        made.append(args[0])
        return empty(*args, **kw)
    monkeypatch.setattr(np, "empty", counted)
    for depth, buffers in ((1, 6), (2, 2)):
        w = Workspace(depth=depth)
        held, made[:] = None, []
        for i in range(6):
            a, lease = w.take(np, (1000,), np.float32)
            a[:] = i
            if held is not None:
                assert np.all(held[0] == i - 1)            # the array still read kept its values
            held = (a, lease)
        assert len(made) == buffers and w.nbytes == 4000 * depth


def test_a_buffer_of_another_stream_or_too_small_gives_way_to_a_new_one():
    w = Workspace(depth=2)
    a, la = w.take(np, (10,), np.uint8)
    b, lb = w.take(np, (10,), np.uint8)                  # a still leased: the second buffer
    del la
    c, lc = w.take(np, (50,), np.uint8)                  # none large enough: the free one (a's) gives way
    assert w.nbytes == 60 and c.ctypes.data not in (a.ctypes.data, b.ctypes.data)
    assert np.all(b == b)                                # b, still leased, is kept
    try:
        Workspace(depth=0)
    except ValueError as e:
        assert "depth must be at least 1" in str(e)
    else:
        raise AssertionError("depth 0 accepted")
