"""The geometry service's copy of the region dictionary and the merges it follows (a part of
:class:`~openfusion.services.geometry.service.GeometryService`, apart from its volume handling):
deltas applied with their merges relabelled in the voxels, a resync from the semantic service's
snapshot (its merge table relabels what a lost delta carried), and the merge pass asked for
before a save. The state it works on (``_lock``, ``volume``, ``replica``, ``_runner``) is the
service's.

Merges (the semantic service decides them, :mod:`openfusion.mapping.merging`): a delta's
``merged_into`` relabels the merged keys' voxels under the lock updates are applied under. A
save on ``control/save`` (what ``openfusion run`` sends at its end, and ``Client.control("save")``)
first asks ``semantic/merge`` for a pass and waits until its delta is applied (``merge_on_save``,
``merge_on_save_timeout_s``), so a saved map holds objects, not fragments; without an answer the map
is saved as it is (``save_merge_failures``). Periodic checkpoints and the last checkpoint on
shutdown (the bus is closed by then) do not ask: the semantic service merges every
``merge_every`` of its frames anyway. When a delta is lost
(a gap in versions) the replica resyncs from the semantic service's snapshot, whose merge table
relabels the voxels of the merges the lost delta carried.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from openfusion.bus import QueryError
from openfusion.bus.health import live_services
from openfusion.mapping import RegionDictionary
from openfusion.services.geometry.parts import ServiceParts, logger
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.endpoints import SEMANTIC_DICTIONARY, SEMANTIC_MERGE
from openfusion.wire.schemas import DictionaryDelta, DictionarySnapshot, MergeRequest

if TYPE_CHECKING:
    pass


class DictionaryFollower(ServiceParts):
    """The dictionary half of the geometry service (mixed into it)."""

    # and the service's helpers (parts.py)

    def on_delta(self, msg: DictionaryDelta) -> None:
        merges = RegionDictionary.merges_of(msg)
        with self._lock:
            applied = self.replica.apply_delta(msg)
            if merges:
                # Merged keys' voxels take the surviving key, so renders, points and answers follow.
                self._count(GeometryCounter.VOXELS_RELABELLED, self.volume.relabel_keys(merges))
                self._map_changed()
            self._dirty = True
        if not applied:
            self._count(GeometryCounter.DICTIONARY_RESYNCS)
            self._resync_dictionary()

    def _resync_dictionary(self) -> None:
        if self._runner is None:
            return
        snapshot = self.replica.fetch_snapshot(self._runner, SEMANTIC_DICTIONARY)
        if snapshot is not None:
            self.apply_snapshot(snapshot)

    def apply_snapshot(self, snapshot: DictionarySnapshot) -> int:
        """Take the semantic service's snapshot as the dictionary, and relabel the voxels of every
        key it says was merged away (a lost delta's merges included); returns the voxels relabelled."""
        with self._lock:
            merges = self.replica.apply_snapshot(snapshot)
            relabelled = self.volume.relabel_keys(merges) if merges else 0
            if relabelled:
                self._map_changed()
                self._dirty = True
        if relabelled:
            self._count(GeometryCounter.VOXELS_RELABELLED, relabelled)
            logger.info("geometry: resynced the dictionary (v%d); %d voxels of %d merged keys relabelled",
                        snapshot.version, relabelled, len(merges))
        return relabelled

    def merge_before_save(self) -> bool:
        """Ask the semantic service for a merge pass and wait until its delta is applied here, so
        the map about to be saved holds objects, not fragments. False (logged and counted; the
        save goes on) when there is no dictionary, merging on save is off or the semantic service
        does not answer."""
        if self._runner is None or not self.section.merge_on_save or self.replica.dictionary is None:
            return False
        timeout_s = self.section.merge_on_save_timeout_s
        session = getattr(self._runner, "session", None)  # None: a bus-free runner double
        if session is not None and "semantic" not in live_services(session, self._runner.keys, timeout_s=1.0):
            # Nobody to run the pass (the semantic service died or was never started): save at once
            # rather than wait merge_on_save_timeout_s for an answer that cannot come.
            logger.info("geometry: saving without a merge pass: no semantic service is alive")
            self._count(GeometryCounter.SAVE_MERGE_FAILURES)
            return False
        try:
            reply = self._runner.call(SEMANTIC_MERGE, MergeRequest(), timeout_s=timeout_s)
        except QueryError as exc:
            logger.info("geometry: saving without a merge pass: the semantic service did not run one (%s)",
                        exc.reason)
            self._count(GeometryCounter.SAVE_MERGE_FAILURES)
            return False
        if not reply.ok:
            logger.info("geometry: saving without a merge pass: %s", reply.message)
            self._count(GeometryCounter.SAVE_MERGE_FAILURES)
            return False
        # The pass's delta was published before the reply; it comes on the delta subscription. If
        # it does not come in time (lost), the snapshot carries the same merges.
        if not self.replica.wait_for_version(reply.dictionary_version, timeout_s):
            logger.warning("geometry: the merge delta (v%d) did not come; resyncing the dictionary",
                           reply.dictionary_version)
            self._count(GeometryCounter.DICTIONARY_RESYNCS)
            self._resync_dictionary()
        self._count(GeometryCounter.SAVE_MERGES)
        logger.info("geometry: merge pass before saving: %d regions merged, %d pruned (dictionary v%d)",
                    reply.regions_merged, reply.regions_pruned, reply.dictionary_version)
        return True
