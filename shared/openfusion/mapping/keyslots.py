"""Region keys of the compact voxels: a uint16 *slot* per voxel and one table slot -> region key.

Why a table
    A voxel's region key was an int32 (4 bytes); the compact layout (:mod:`openfusion.mapping.storage`,
    16 bytes per voxel) stores a uint16 slot instead, and this table says which region key each
    slot stands for. Region keys themselves stay int32 and unbounded (the dictionary hands out
    ever-growing keys): only the number of *distinct keys present in voxels at one time* is bounded
    by the slot count (65,535).

    The table is also what makes key rewrites cheap at the scale of a building: a merge ``{b: a}``
    or a cleared key ``{b: -1}`` is one change of the table (every slot that stood for ``b`` now
    stands for ``a``), not a pass over every voxel -- including the voxels of tiles paged out to
    the tile store, which would otherwise have to be read, rewritten and written back.

Slot 0 is "no key". A merge leaves the merged key's slots as *aliases* of the surviving key; a
cleared key leaves them standing for -1. Both are garbage that :meth:`KeySlots.compaction_map`
reclaims: when no free slot is left the owner rewrites every voxel (resident and stored) through
that map, and the slots no voxel uses any more become free again. Only when 65,535 distinct keys
really are present in voxels at once does :meth:`KeySlots.slots_for` raise
:class:`~openfusion.mapping.errors.CapacityError` (nothing written).

Keys are handled in the volume's stored form *key + 1* (0 = none) everywhere below, as the update
rule speaks it (:mod:`openfusion.mapping.update_rule`).
"""

from __future__ import annotations

import numpy as np

from openfusion.mapping.errors import CapacityError

#: Slots a uint16 voxel attribute can name (slot 0 = no key).
MAX_SLOTS = 65535


class KeySlots:
    """The slot -> key table of one volume (``key1`` = key + 1 per slot, 0 for slot 0 and free slots)."""

    def __init__(self, max_slots: int = MAX_SLOTS) -> None:
        if not 1 <= max_slots <= MAX_SLOTS:
            raise ValueError(f"max_slots must be within [1, {MAX_SLOTS}], got {max_slots}")
        self.max_slots = int(max_slots)
        #: key + 1 of every slot (index 0 and free slots: 0). Read through :meth:`key1_of`.
        self.key1 = np.zeros(self.max_slots + 1, np.int32)
        self._slot_of_key1: dict[int, int] = {}  # key + 1 -> the slot new voxels of that key take
        self._in_use = np.zeros(self.max_slots + 1, bool)  # slots handed out (aliases included)
        self._in_use[0] = True
        self.version = 0  # bumped by every change of the table (maps store it with the tiles)

    # ------------------------------------------------------------------ reading
    def key1_of(self, slots: np.ndarray) -> np.ndarray:
        """Stored keys (key + 1, int32) of voxel slots (any unsigned integer array)."""
        return self.key1[np.asarray(slots, np.intp)]

    @property
    def free_slots(self) -> int:
        return int(self.max_slots + 1 - self._in_use.sum())

    @property
    def used_slots(self) -> int:
        return int(self._in_use.sum()) - 1

    # ------------------------------------------------------------------ writing
    def slots_for(self, key1: np.ndarray, *, compact: object = None) -> np.ndarray:
        """Slots (uint16) for stored keys (key + 1, >= 0; 0 -> slot 0), allocating slots for keys
        that have none. ``compact``: a callable the table calls (once) when it runs out of slots;
        it must rewrite every voxel through :meth:`compaction_map` and call :meth:`compacted`.
        Raises :class:`CapacityError` when even then too few slots are free (table unchanged)."""
        key1 = np.asarray(key1, np.int64)
        uniq, inverse = np.unique(key1, return_inverse=True)
        missing = [int(k) for k in uniq if k > 0 and int(k) not in self._slot_of_key1]
        if len(missing) > self.free_slots and callable(compact):
            compact()
        if len(missing) > self.free_slots:
            raise CapacityError(
                f"{self.used_slots + len(missing)} distinct region keys would be present in voxels at once; "
                f"the compact voxel layout holds {self.max_slots}",
                blocks_needed=len(missing),
                blocks_free=self.free_slots,
            )
        if missing:
            free = np.flatnonzero(~self._in_use)[: len(missing)]
            for k, slot in zip(missing, free, strict=True):
                self._assign(int(slot), k)
            self.version += 1
        out = np.zeros(len(uniq), np.uint16)
        for i, k in enumerate(uniq):
            if k > 0:
                out[i] = self._slot_of_key1[int(k)]
        return out[inverse.reshape(-1)].reshape(key1.shape)

    def _assign(self, slot: int, key1: int) -> None:
        self.key1[slot] = key1
        self._in_use[slot] = True
        self._slot_of_key1[key1] = slot

    def relabel(self, mapping: dict[int, int]) -> np.ndarray:
        """Apply ``{old key: new key}`` (new -1 clears) to the table, all pairs at once (``{1: 2,
        2: 3}`` moves 1 to 2 and 2 to 3, not 1 to 3); returns the slots whose key changed (their
        voxels now read the new key). No voxel is touched."""
        pairs: dict[int, int] = {}
        for old, new in mapping.items():
            old1, new1 = int(old) + 1, int(new) + 1
            if old1 <= 0 or new1 < 0:
                raise ValueError(f"cannot relabel {old} -> {new}: keys are >= 0 (-1 only as target)")
            if old1 != new1:
                pairs[old1] = new1
        if not pairs:
            return np.zeros(0, np.int64)
        olds = np.fromiter(pairs.keys(), np.int64)
        news = np.fromiter(pairs.values(), np.int64)
        hit = np.isin(self.key1, olds)
        hit[0] = False
        changed = np.flatnonzero(hit)
        if len(changed) == 0:
            return changed
        order = np.argsort(olds)
        pos = np.searchsorted(olds[order], self.key1[changed])
        self.key1[changed] = news[order][pos]
        # Canonical slots: keep those that still read their key; find one for keys that lost theirs.
        for key1 in list(self._slot_of_key1):
            if self.key1[self._slot_of_key1[key1]] != key1:
                del self._slot_of_key1[key1]
        for key1 in set(news.tolist()):
            if key1 > 0 and key1 not in self._slot_of_key1:
                holders = np.flatnonzero(self.key1 == key1)
                holders = holders[holders > 0]
                if len(holders):
                    self._slot_of_key1[key1] = int(holders[0])
        self.version += 1
        return changed

    # ------------------------------------------------------------------ compaction
    def compaction_map(self) -> np.ndarray:
        """uint16 map old slot -> new slot: every alias to its key's own slot, every slot of a
        cleared key to 0. Rewriting voxels through it leaves only canonical slots in use."""
        remap = np.zeros(self.max_slots + 1, np.uint16)
        for key1, slot in self._slot_of_key1.items():
            remap[self.key1 == key1] = slot
        remap[0] = 0
        return remap

    def compacted(self, remap: np.ndarray, used_after: np.ndarray | None = None) -> None:
        """The owner rewrote every voxel through ``remap``: free every slot that is not the target
        of a live key (and, given ``used_after``, the slots present in voxels afterwards, which no voxel uses)."""
        keep = np.zeros(self.max_slots + 1, bool)
        keep[np.unique(remap)] = True
        if used_after is not None:
            present = np.zeros(self.max_slots + 1, bool)
            present[np.asarray(used_after, np.intp)] = True
            keep &= present
        keep[0] = True
        for slot in np.flatnonzero(self._in_use & ~keep):
            k = int(self.key1[slot])
            if self._slot_of_key1.get(k) == int(slot):
                del self._slot_of_key1[k]
            self.key1[slot] = 0
        self._in_use = keep.copy()
        # A live key whose canonical slot was freed (no voxel holds it) gets one on next use.
        self.version += 1

    # ------------------------------------------------------------------ persistence
    def to_array(self) -> np.ndarray:
        """int32 (max_slots + 1,): key + 1 per slot, -1 for free slots (what a map stores)."""
        out = self.key1.copy()
        out[~self._in_use] = -1
        out[0] = 0
        return out

    @classmethod
    def from_array(cls, table: np.ndarray, max_slots: int = MAX_SLOTS) -> KeySlots:
        """Inverse of :meth:`to_array`; ``ValueError`` for a table of the wrong shape or values."""
        table = np.asarray(table)
        if table.ndim != 1 or len(table) < 1 or len(table) > max_slots + 1 or not np.issubdtype(table.dtype, np.integer):
            raise ValueError(f"key slot table must be 1-D integers of at most {max_slots + 1} entries")
        if len(table) and (int(table.min()) < -1):
            raise ValueError("key slot table values must be >= -1")
        slots = cls(max_slots)
        for slot in np.flatnonzero(table > 0):
            k = int(table[slot])
            slots.key1[slot] = k
            slots._in_use[slot] = True
            slots._slot_of_key1.setdefault(k, int(slot))
        for slot in np.flatnonzero(table == 0)[1:] if len(table) else []:
            slots._in_use[slot] = True  # a cleared key's slot: garbage until compaction
        return slots
