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

