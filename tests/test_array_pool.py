"""io.array_pool: host arrays used again only once nothing but the pool holds them; pinned blocks (page-locked
for the GPU's copies) pinned once, in whole pages of their own, and unpinned when freed."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from whitecap.io.array_pool import PAGE, ArrayPool

LAYOUT = {"x": (np.float32, (3,)), "kind": (np.uint8, ())}


def _base(a: np.ndarray) -> np.ndarray:
    return a if a.base is None else a.base


class FakePinning:
    """pin and unpin as the CUDA driver's are called, recorded: (address, bytes) pinned, addresses unpinned."""

    def __init__(self, ok: bool = True) -> None:
        self.ok, self.pinned, self.unpinned = ok, [], []

    def pin(self, address: int, nbytes: int) -> bool:
        self.pinned.append((address, nbytes))
        return self.ok

    def unpin(self, address: int) -> None:
        self.unpinned.append(address)


@pytest.fixture(params=["plain", "pinned"])
def pool_of(request):
    """ArrayPool(LAYOUT, keep) as the solver makes it on the CPU (plain) and on CUDA with pinning (pinned)."""
    def make(keep: int) -> ArrayPool:
        if request.param == "plain":
            return ArrayPool(LAYOUT, keep=keep)
        fake = FakePinning()
        return ArrayPool(LAYOUT, keep=keep, pin=fake.pin, unpin=fake.unpin)
    return make


def test_a_block_is_used_again_once_its_views_are_gone(pool_of):
    pool = pool_of(2)
    a = pool.take(100)
    assert a["x"].shape == (100, 3) and a["x"].dtype == np.float32 and a["kind"].shape == (100,)
    first = id(_base(a["x"]))  # (the id alone: a reference to the array would keep the block busy)
    del a
    b = pool.take(90)  # fewer rows: the same block
    assert id(_base(b["x"])) == first and pool.made == 1
    assert b["x"].flags.c_contiguous and b["kind"].flags.c_contiguous


@pytest.mark.parametrize("hold", ["view", "slice of a view", "other array", "memoryview"])
def test_a_block_anything_still_holds_is_never_handed_out_again(hold, pool_of):
    pool = pool_of(3)
    a = pool.take(50)
    a["x"][:] = 7.0
    a["kind"][:] = 3
    if hold == "view":
        kept = a["x"]
    elif hold == "slice of a view":
        kept = a["x"][10:20, 1]
    elif hold == "other array":
        kept = a["kind"]
    else:
        kept = memoryview(a["kind"])
    del a
    for _ in range(5):  # every later frame gets other memory, and writes all of it
        b = pool.take(50)
        b["x"][:] = -1.0
        b["kind"][:] = 0
        del b
    if hold == "memoryview":
        assert (np.frombuffer(kept, np.uint8) == 3).all()
    else:
        assert (np.asarray(kept) == (3 if hold == "other array" else 7.0)).all()


def test_busy_blocks_beyond_keep_are_made_and_not_kept(pool_of):
    pool = pool_of(2)
    held = [pool.take(10) for _ in range(4)]  # all held: four blocks, two of them kept
    bases = {id(_base(h["x"])) for h in held}
    assert len(bases) == 4 and pool.made == 4
    del held
    for _ in range(6):  # frames handed out one at a time and dropped: the kept blocks alone
        pool.take(10)
    assert pool.made == 4
    # the two kept blocks' arrays; pinned, each array in whole pages, the buffer a page more for its alignment
    assert pool.nbytes in (2 * int(10 * 1.125) * (12 + 1), 2 * 3 * PAGE)


def test_a_pinned_block_is_whole_pages_of_its_own_pinned_once_and_unpinned_when_freed():
    fake = FakePinning()
    pool = ArrayPool({"x": (np.float32, (3,)), "kind": (np.uint8, ()), "ids": (np.uint32, ())}, keep=1,
                     pin=fake.pin, unpin=fake.unpin)
    a = pool.take(1000)
    address, nbytes = fake.pinned[0]
    assert address % PAGE == 0 and nbytes % PAGE == 0 and pool.pinned == 1
    for k, arr in a.items():  # each array on pages of its own, all inside the pinned range
        lo = arr.ctypes.data
        assert lo % PAGE == 0 and address <= lo and lo + arr.nbytes <= address + nbytes, k
    ends = sorted((arr.ctypes.data, arr.ctypes.data + arr.nbytes) for arr in a.values())
    assert all(e0 <= s1 for (_, e0), (s1, _) in zip(ends, ends[1:]))  # no overlap
    a["x"][:] = 1.0
    del a, arr  # (the loop's last view too)
    for _ in range(3):  # used again: pinned once
        pool.take(900)
    assert len(fake.pinned) == 1 and fake.unpinned == []
    held = pool.take(1000)["ids"][5:9]  # a slice of a view holds the buffer
    pool.take(5000)  # the kept block busy: a block for this frame alone, not kept, not pinned
    gc.collect()
    assert fake.unpinned == [] and len(fake.pinned) == 1 and pool.made == 2
    del held
    pool.take(5000)  # the kept block free but too small: replaced by a larger one, pinned, and it is freed
    gc.collect()
    assert fake.unpinned == [address] and len(fake.pinned) == 2  # freed: unpinned, once
    del pool
    gc.collect()
    assert fake.unpinned == [address, fake.pinned[1][0]]


def test_a_block_the_driver_would_not_pin_is_used_unpinned():
    fake = FakePinning(ok=False)
    pool = ArrayPool(LAYOUT, keep=1, pin=fake.pin, unpin=fake.unpin)
    a = pool.take(100)
    a["x"][:] = 2.0
    assert pool.pinned == 0 and len(fake.pinned) == 1
    del a
    assert (pool.take(100)["x"] == 2.0).all() and pool.made == 1  # the same block, kept
    del pool
    gc.collect()
    assert fake.unpinned == []  # never pinned: never unpinned


def test_a_block_too_small_is_replaced_by_a_larger_one_with_room_to_grow():
    pool = ArrayPool(LAYOUT, keep=1)
    pool.take(100)
    b = pool.take(120)  # larger than the block: a new one, kept in its place
    assert pool.made == 2 and len(_base(b["x"])) >= 120
    del b
    pool.take(int(120 * 1.1))  # within the growth room: no new block
    assert pool.made == 2


def test_an_empty_frame_and_keep_below_one():
    pool = ArrayPool(LAYOUT)
    assert pool.take(0)["x"].shape == (0, 3)
    assert pool.take(5)["x"].shape == (5, 3)
    with pytest.raises(ValueError):
        ArrayPool(LAYOUT, keep=0)


def test_a_free_block_large_enough_is_taken_before_a_small_one_is_replaced():
    pool = ArrayPool(LAYOUT, keep=2)
    small = pool.take(10)
    large = pool.take(100)  # both held: two kept blocks, the first of 11 rows, the second of 112
    large_id = id(_base(large["x"]))
    del small, large
    got = pool.take(50)  # the first free block is too small, the second fits
    assert id(_base(got["x"])) == large_id and pool.made == 2


def test_a_small_free_block_behind_a_busy_one_is_replaced():
    pool = ArrayPool(LAYOUT, keep=2)
    held = pool.take(100)  # busy throughout
    small = pool.take(10)
    del small
    got = pool.take(50)  # the free block is too small: replaced by one of 56 rows, kept in its place
    assert pool.made == 3 and len(_base(got["x"])) == int(50 * 1.125)
    del got
    assert id(_base(pool.take(50)["x"])) != id(_base(held["x"])) and pool.made == 3
