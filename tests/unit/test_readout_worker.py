"""The read-out worker (map core, no bus): whole-map read-outs asked for on several threads at once
run one chunk at a time, and decoded tiles exist only inside that one chunk.

Bad input tried: a read-out asked for while holding the volume's lock (refused at once with
``WorkerOrderError``, never a hang), and a job that raises (the asker gets the error, the worker
goes on with the next job)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from openfusion.mapping import SemanticVolume, VolumeParams, readout_worker
from openfusion.mapping import chunkreadouts as chunk_mod
from openfusion.mapping import paging as paging_mod
from openfusion.mapping import tilereadouts as readouts_mod
from openfusion.mapping.mapstore import checkpoint
from openfusion.mapping.readout_worker import WorkerOrderError
from openfusion.mapping.tilestore import TileStore
from openfusion.sources import open_source

FRAMES = list(open_source("synthetic:seed=1,frames=12,width=160,height=120,lap=12"))
BASE = {"voxel_size_m": 0.04, "tile_blocks": 2, "depth_max_m": 4.0}
K = FRAMES[0].intrinsics.scaled(80, 60)


def _labelled(volume: SemanticVolume, frames: list) -> None:  # noqa: ANN001
    for i, f in enumerate(frames):
        volume.integrate(f)
        if i % 3 == 0:
            keys = (np.arange(80)[None].repeat(60, 0) // 10 + i).astype(np.int32)
            volume.apply_update(f.T_world_cam, K, keys, np.full((60, 80), 0.7, np.float32))


@pytest.fixture(scope="module")
def paged(tmp_path_factory: pytest.TempPathFactory) -> SemanticVolume:
    """The room mapped with keys under a budget of 75 % of its blocks, checkpointing into a store."""
    probe = SemanticVolume(VolumeParams(**BASE))
    _labelled(probe, FRAMES)
    budget = 0.75 * probe.num_blocks * 8192 / 2**20
    probe.close()
    store = TileStore(tmp_path_factory.mktemp("worker") / "map.ofz")
    volume = SemanticVolume(VolumeParams(**BASE, memory_budget_mb=budget), store=store)
    _labelled(volume, FRAMES)
    assert volume.pager.stored_blocks
    yield volume
    volume.close()


class _Ledger:
    """The test hook: jobs in hand at once, and every decode of a stored tile with the thread it ran
    on and whether a job was in hand then."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.in_hand = 0
        self.most = 0
        self.jobs: list[str] = []
        self.decodes: list[tuple[bool, bool, int]] = []  # (on the worker, inside a job, blocks)

    def hook(self, event: str, what: str) -> None:
        with self.lock:
            if event == "start":
                self.in_hand += 1
                self.most = max(self.most, self.in_hand)
                self.jobs.append(what)
            else:
                self.in_hand -= 1

    def wrap(self, decode):  # noqa: ANN001, ANN201
        def counted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            coords, raw = decode(*args, **kwargs)
            with self.lock:
                self.decodes.append((readout_worker.on_worker(), self.in_hand == 1, len(coords)))
            return coords, raw

        return counted


def test_concurrent_read_outs_never_hold_more_than_one_chunk(paged: SemanticVolume, tmp_path, monkeypatch) -> None:  # noqa: ANN001
    """Points, a mesh, region summaries, region contacts and a checkpoint asked for on five threads at
    once: every decoded stored tile is decoded on the worker inside a job, never two jobs are in
    hand at once, and each read-out gives what it gives asked for alone."""
    v = paged
    for f in FRAMES[:3]:  # a change for the checkpoint to write
        v.integrate(f)
    alone_points = v.extract_points()
    alone_table = v.region_table()
    alone_contacts = v.region_contacts()
    v._readouts.forget()  # read every tile out again below, on five threads
    ledger = _Ledger()
    monkeypatch.setattr(paging_mod, "decode_tile", ledger.wrap(paging_mod.decode_tile))
    monkeypatch.setattr(chunk_mod, "decode_tile", ledger.wrap(chunk_mod.decode_tile))
    monkeypatch.setattr(readouts_mod, "CHUNK_BLOCKS", 64)  # many chunks: the read-outs interleave
    readout_worker.hooks.append(ledger.hook)
    results: dict[str, object] = {}
    errors: list[BaseException] = []
    go = threading.Barrier(5)

    def ask(name: str, fn) -> None:  # noqa: ANN001
        go.wait()
        try:
            results[name] = fn()
        except BaseException as exc:  # handed to the test thread
            errors.append(exc)

    work = {
        "points": v.extract_points,
        "mesh": v.extract_mesh,
        "summaries": v.region_table,
        "contacts": v.region_contacts,
        "checkpoint": lambda: checkpoint(v, None, {"frames": 1}),
    }
    try:
        threads = [threading.Thread(target=ask, args=(n, f)) for n, f in work.items()]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        readout_worker.hooks.remove(ledger.hook)
    assert not errors, errors
    assert ledger.most == 1, f"{ledger.most} jobs were in hand at once"
    assert len(ledger.decodes) > 20  # stored tiles were decoded (the test exercised what it counts)
    assert all(on and inside for on, inside, _ in ledger.decodes), "a tile was decoded outside the worker's one job"
    kinds = set(ledger.jobs)
    assert {"extract_points", "extract_mesh", "summaries", "contacts", "checkpoint"} <= kinds
    # The read-outs interleaved chunk by chunk (FIFO), not one after the other.
    first = {k: ledger.jobs.index(k) for k in ("summaries", "contacts")}
    last = {k: len(ledger.jobs) - 1 - ledger.jobs[::-1].index(k) for k in ("summaries", "contacts")}
    assert first["contacts"] < last["summaries"] and first["summaries"] < last["contacts"]
    got = results["points"]
    np.testing.assert_array_equal(got.points, alone_points.points)  # type: ignore[attr-defined]
    np.testing.assert_array_equal(got.keys, alone_points.keys)  # type: ignore[attr-defined]
    table = results["summaries"]
    np.testing.assert_array_equal(table.keys, alone_table.keys)  # type: ignore[attr-defined]
    np.testing.assert_array_equal(table.bbox_min, alone_table.bbox_min)  # type: ignore[attr-defined]
    contacts = results["contacts"]
    for name in ("keys", "surface_voxels", "pair_a", "pair_b", "contact_a", "contact_b"):
        np.testing.assert_array_equal(getattr(contacts, name), getattr(alone_contacts, name), err_msg=name)
    assert len(results["mesh"].triangles) > 0  # type: ignore[attr-defined]


def test_a_read_out_asked_for_under_the_volume_lock_is_refused_not_hung(paged: SemanticVolume) -> None:
    """Rule 1 of the worker: a thread holding a lock a job takes is refused at once (a bug in the
    caller), and the volume goes on working afterwards."""
    with paged.locked(), pytest.raises(WorkerOrderError):
        paged.extract_points()
    service_lock = threading.RLock()
    handle = readout_worker.register_lock(service_lock)
    try:
        with service_lock, pytest.raises(WorkerOrderError):
            paged.region_contacts(lock=service_lock)
    finally:
        readout_worker.unregister_lock(handle)
    assert len(paged.extract_points()) > 0


def test_a_failing_job_reaches_its_asker_and_the_worker_goes_on() -> None:
    def broken() -> None:
        raise ValueError("a corrupt chunk")

    with pytest.raises(ValueError, match="corrupt chunk"):
        readout_worker.run("broken", broken)
    assert readout_worker.run("fine", lambda: 42) == 42
    # A job asking for another read-out runs it inline (never queued behind itself).
    assert readout_worker.run("outer", lambda: readout_worker.run("inner", lambda: 7)) == 7


def test_renders_read_resident_blocks_and_take_no_job(paged: SemanticVolume) -> None:
    """A render pages in what its view reaches and reads the grid: it never waits for the worker."""
    jobs = readout_worker.STATS["jobs"]
    seen: list[str] = []

    def hook(event: str, what: str) -> None:
        seen.append(what)

    readout_worker.hooks.append(hook)
    try:
        view = paged.render(FRAMES[0].T_world_cam, K)
    finally:
        readout_worker.hooks.remove(hook)
    assert (view.depth_m > 0).any()
    assert readout_worker.STATS["jobs"] == jobs and not seen


def test_summaries_that_do_not_settle_are_read_holding_the_locks_in_one_job(paged: SemanticVolume, monkeypatch) -> None:  # noqa: ANN001
    """When the parts kept too few values three times (a map changing under the read-outs), the
    fourth try reads holding both locks throughout, as one job of the worker, asked for by a thread
    that holds neither (a service's save came here and failed before)."""
    from openfusion.mapping import tilereadouts

    real = tilereadouts.combine_summaries
    calls = {"n": 0}

    def unsettled(parts, key1, *args, index=None):  # noqa: ANN001, ANN002, ANN202
        calls["n"] += 1
        table, failing = real(parts, key1, *args, index=index)
        labelled = [(t, part) for t, part in (index if index is not None else parts) if len(part.slots)]
        if calls["n"] <= 3 and labelled:
            t, part = labelled[0]
            failing = {(t, int(part.slots[0])): 1}
        return table, failing

    monkeypatch.setattr(tilereadouts, "combine_summaries", unsettled)
    service_lock = threading.RLock()
    handle = readout_worker.register_lock(service_lock)
    seen: list[str] = []

    def hook(event: str, what: str) -> None:
        if event == "start":
            seen.append(what)

    readout_worker.hooks.append(hook)
    try:
        table = paged.region_table(lock=service_lock)
    finally:
        readout_worker.hooks.remove(hook)
        readout_worker.unregister_lock(handle)
    assert calls["n"] >= 4 and "summaries" in seen
    monkeypatch.setattr(tilereadouts, "combine_summaries", real)
    np.testing.assert_array_equal(table.keys, paged.region_table().keys)


def test_a_checkpoint_whose_passes_fall_behind_encodes_its_last_step_tile_by_tile(tmp_path, monkeypatch) -> None:  # noqa: ANN001
    """When more than a slice of changed tiles is left for a checkpoint's last step (the camera
    changed them faster than the passes wrote them), the step copies and encodes one tile at a time
    instead of copying them all at once; the store then holds the map exactly."""
    from openfusion.mapping import load_map, mapstore, paging

    monkeypatch.setattr(mapstore, "PRECOPY_PASSES_MAX", 0)  # no pass: everything is left to the last step
    monkeypatch.setattr(paging, "SLICE_BLOCKS", 64)
    encoded: list[int] = []
    real = paging.TilePager.encode

    def counting(self, tiles):  # noqa: ANN001, ANN202
        encoded.append(len(tiles))
        return real(self, tiles)

    monkeypatch.setattr(paging.TilePager, "encode", counting)
    volume = SemanticVolume(VolumeParams(**BASE), store=TileStore(tmp_path / "map.ofz"))
    try:
        for f in FRAMES[:4]:
            volume.integrate(f)
        info = checkpoint(volume, None, {})
        assert info["tiles"] == len(volume.pager.all_tiles()) > 1
        assert max(encoded[:-1]) == 1  # one tile per copy under the lock (the last call: the empty rest)
        loaded = load_map(tmp_path)
        a, b = loaded.volume.to_arrays(), volume.to_arrays()
        order_a, order_b = np.lexsort(a["block_coords"].T), np.lexsort(b["block_coords"].T)
        for name in a:
            np.testing.assert_array_equal(a[name][order_a], b[name][order_b], err_msg=name)
        assert not volume.pager.precopy_plan()  # every tile clean and located in the store
        assert all(volume.pager.location.get(t) == "own" for t in volume.pager.all_tiles())
        loaded.volume.close()
    finally:
        volume.close()
