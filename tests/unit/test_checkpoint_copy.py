"""A checkpoint copied as files between two geometry processes (openfusion.mapping.checkpoint_copy,
no bus): a snapshot of the committed checkpoint only, served in chunks, written and checked on the
other side, installed and loaded as the same map.

Bad input tried: a chunk whose bytes were flipped in transit (digest), a chunk out of place (a
skipped offset), a chunk past the file's end, a file whose whole digest disagrees with the listing,
a copy cut short (incomplete), a copy whose bytes are right but not a map, file names that would
escape the folder (``..``, absolute, hidden) in the wire schema, a folder with no checkpoint, a
snapshot that cannot be written."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from openfusion.mapping import RegionDictionary, SemanticVolume, VolumeParams, load_map
from openfusion.mapping.checkpoint_copy import (
    CheckpointCopyError,
    CopyReceiver,
    FileEntry,
    install_copy,
    read_chunk,
    snapshot_checkpoint,
    verify_store,
)
from openfusion.mapping.mapstore import checkpoint
from openfusion.mapping.tilestore import TileStore
from openfusion.sources import open_source
from openfusion.wire.schemas import CheckpointChunkRequest, CheckpointFile

FRAMES = list(open_source("synthetic:seed=1,frames=10,width=120,height=90"))
PARAMS = VolumeParams(voxel_size_m=0.05, tile_blocks=2, depth_max_m=4.0)
CHUNK = 64 * 1024


def _checkpointed(folder: Path, frames: list) -> SemanticVolume:  # noqa: ANN001
    volume = SemanticVolume(PARAMS, store=TileStore(folder / "map.ofz"))
    for f in frames:
        volume.integrate(f)
    checkpoint(volume, RegionDictionary("none", 1), {"last_frame_id": frames[-1].frame_id,
                                                     "frames_integrated": len(frames)})
    return volume


def _copy(snapshot, into: Path) -> CopyReceiver:  # noqa: ANN001
    receiver = CopyReceiver(snapshot.files, into)
    for f in snapshot.files:
        while not receiver.done(f.name):
            data = read_chunk(snapshot, f.name, receiver.next_offset(f.name), CHUNK)
            receiver.write(f.name, receiver.next_offset(f.name), data, hashlib.sha256(data).hexdigest())
    receiver.finish()
    return receiver


def test_a_snapshot_holds_the_committed_checkpoint_and_copies_to_the_same_map(tmp_path: Path) -> None:
    volume = _checkpointed(tmp_path / "peer", FRAMES[:6])
    committed = volume.extract_points().points
    for f in FRAMES[6:]:  # integrated after the checkpoint: not in the snapshot
        volume.integrate(f)
    snap = snapshot_checkpoint(tmp_path / "peer", tmp_path / "peer" / ".snapshots")
    assert [f.name for f in snap.files] == ["map.ofz/data.mdb"]  # LMDB's lock file is not data
    assert snap.last_frame_id == FRAMES[5].frame_id and snap.frames_integrated == 6 and snap.tiles > 0
    assert snap.total_bytes > CHUNK  # several chunks
    receiver = _copy(snap, tmp_path / "replica" / ".incoming")
    assert receiver.bytes_written == snap.total_bytes
    info = verify_store(tmp_path / "replica" / ".incoming")
    assert info["last_frame_id"] == FRAMES[5].frame_id and info["tiles"] == snap.tiles
    install_copy(tmp_path / "replica" / ".incoming", tmp_path / "replica")
    assert not (tmp_path / "replica" / ".incoming").exists()
    loaded = load_map(tmp_path / "replica")
    try:
        np.testing.assert_array_equal(np.sort(loaded.volume.extract_points().points, axis=0), np.sort(committed, axis=0))
        assert loaded.meta["frames_integrated"] == 6
    finally:
        loaded.volume.close()
        volume.close()
        snap.remove()
    assert not snap.folder.exists()


def test_bad_chunks_and_bad_copies_are_refused(tmp_path: Path) -> None:
    volume = _checkpointed(tmp_path / "peer", FRAMES[:4])
    snap = snapshot_checkpoint(tmp_path / "peer", tmp_path / "snaps")
    volume.close()
    name = snap.files[0].name
    first = read_chunk(snap, name, 0, CHUNK)
    r = CopyReceiver(snap.files, tmp_path / "a")
    flipped = bytearray(first)
    flipped[100] ^= 0xFF  # corrupt in transit: the chunk's digest is the peer's, of the right bytes
    with pytest.raises(CheckpointCopyError, match="SHA-256") as err:
        r.write(name, 0, bytes(flipped), hashlib.sha256(first).hexdigest())
    assert err.value.reason == "bad_digest" and r.next_offset(name) == 0  # nothing of it written
    second = read_chunk(snap, name, CHUNK, CHUNK)
    with pytest.raises(CheckpointCopyError, match="expected 0") as err:  # a chunk out of place
        r.write(name, CHUNK, second, hashlib.sha256(second).hexdigest())
    assert err.value.reason == "bad_chunk"
    with pytest.raises(CheckpointCopyError, match="listing does not name"):
        r.write("map.ofz/other.mdb", 0, first, hashlib.sha256(first).hexdigest())
    r.write(name, 0, first, hashlib.sha256(first).hexdigest())
    with pytest.raises(CheckpointCopyError, match="copied") as err:  # cut short: the peer went away
        r.finish()
    assert err.value.reason == "incomplete"
    r.discard()
    assert not (tmp_path / "a").exists()
    # Past the end of the file, on either side.
    size = snap.files[0].size_bytes
    with pytest.raises(CheckpointCopyError, match="outside"):
        read_chunk(snap, name, size + 1, CHUNK)
    r = CopyReceiver([FileEntry(name, 10, snap.files[0].sha256)], tmp_path / "b")
    with pytest.raises(CheckpointCopyError, match="does not fit"):
        r.write(name, 0, first, hashlib.sha256(first).hexdigest())
    # Every chunk right but the listing's digest of the whole file is not this file's.
    wrong = [FileEntry(name, size, "0" * 64)]
    r = CopyReceiver(wrong, tmp_path / "c")
    for offset in range(0, size, CHUNK):
        data = read_chunk(snap, name, offset, CHUNK)
        r.write(name, offset, data, hashlib.sha256(data).hexdigest())
    with pytest.raises(CheckpointCopyError, match="listing's SHA-256") as err:
        r.finish()
    assert err.value.reason == "bad_digest"
    # Bytes that match their digests but are not a map (a peer serving garbage): not installed.
    junk = tmp_path / "d" / "map.ofz"
    junk.mkdir(parents=True)
    (junk / "data.mdb").write_bytes(b"\0" * 8192)
    with pytest.raises(CheckpointCopyError) as err:
        verify_store(tmp_path / "d")
    assert err.value.reason == "bad_map"
    snap.remove()


def test_no_checkpoint_no_snapshot_and_names_cannot_escape(tmp_path: Path) -> None:
    with pytest.raises(CheckpointCopyError) as err:
        snapshot_checkpoint(tmp_path / "empty", tmp_path / "snaps")
    assert err.value.reason == "no_checkpoint"
    TileStore(tmp_path / "fresh" / "map.ofz").close()  # a store never committed: nothing to serve either
    with pytest.raises(CheckpointCopyError, match="no checkpoint yet"):
        snapshot_checkpoint(tmp_path / "fresh", tmp_path / "snaps")
    assert not any((tmp_path / "snaps").glob("*")) if (tmp_path / "snaps").exists() else True
    # A snapshot that cannot be written (here: a file where its folder goes; a full disk alike) is said.
    _checkpointed(tmp_path / "peer", FRAMES[:2]).close()
    (tmp_path / "not-a-folder").write_text("x")
    with pytest.raises(CheckpointCopyError, match="could not snapshot") as err:
        snapshot_checkpoint(tmp_path / "peer", tmp_path / "not-a-folder")
    assert err.value.reason == "snapshot_failed"
    for bad in ("../x", "/etc/passwd", "map.ofz/../../x", ".hidden", "a/*/b", "a//b", ""):
        with pytest.raises(ValidationError, match="checkpoint file name"):
            CheckpointFile(name=bad, size_bytes=1, sha256="0" * 64)
        with pytest.raises(ValidationError):
            CheckpointChunkRequest(snapshot_id="0" * 32, name=bad, offset_bytes=0, length_bytes=1)
    with pytest.raises(ValidationError):  # more than one reply's worth
        CheckpointChunkRequest(snapshot_id="0" * 32, name="map.ofz/data.mdb", offset_bytes=0, length_bytes=1 << 30)
