#!/usr/bin/env python3
"""Why the tile store is LMDB + zstd: the tiles of the built-in room written and read back through
LMDB and through SQLite (the standard library's embedded store, WAL mode, one row per tile), each
with zstd and lz4 on byte-shuffled attributes, in one run; and the map's bytes per voxel.

Measured per store and codec: encode + write of every tile in one transaction (a full
checkpoint), write of 10 % of them (an incremental one), read + decode of every tile (a load), and
the size on disk. Ratios are against LMDB + zstd, measured in the same run.

    .venv/bin/python bench/bench_tilestore.py            # 60 frames of the room at 320x240, 2 cm
    .venv/bin/python bench/bench_tilestore.py --full     # 120 frames at 640x480
"""

from __future__ import annotations

import argparse
import sqlite3
import sys
import tempfile
import time
from pathlib import Path

from openfusion.mapping.tiles import tile_key
from openfusion.mapping.tilestore import TileStore, decode_tile, encode_tile, make_codec
from openfusion.sources import open_source
from openfusion.testing.maps import volume_with_every_tile


class _Sqlite:
    """The alternative: SQLite in WAL mode, ``tiles(key BLOB PRIMARY KEY, blob BLOB)``."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.db = sqlite3.connect(path / "tiles.sqlite")
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute("PRAGMA synchronous=FULL")
        self.db.execute("CREATE TABLE IF NOT EXISTS tiles(key BLOB PRIMARY KEY, blob BLOB)")

    def write(self, blobs: dict[tuple[int, int, int], bytes]) -> None:
        with self.db:
            self.db.executemany("INSERT OR REPLACE INTO tiles VALUES (?, ?)", [(tile_key(t), b) for t, b in blobs.items()])
        self.db.execute("PRAGMA wal_checkpoint(TRUNCATE)")

    def read_all(self) -> list[bytes]:
        return [bytes(r[0]) for r in self.db.execute("SELECT blob FROM tiles")]

    def size(self) -> int:
        return sum(f.stat().st_size for f in self.path.iterdir())


class _Lmdb:
    def __init__(self, path: Path, codec: str) -> None:
        self.store = TileStore(path / "map.ofz", codec=codec)

    def write(self, blobs: dict[tuple[int, int, int], bytes]) -> None:
        self.store.commit(blobs=blobs, header={"bench": True}, arrays={})

    def read_all(self) -> list[bytes]:
        return [b for _, b in self.store.iter_committed()]

    def size(self) -> int:
        return self.store.size_bytes()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="60 frames at 320x240 (default)")
    size.add_argument("--full", action="store_true", help="120 frames at 640x480")
    args = parser.parse_args(argv)
    frames, w, h = (120, 640, 480) if args.full else (60, 320, 240)
    volume, tiles = volume_with_every_tile(open_source(f"synthetic:seed=1,frames={frames},width={w},height={h}"))
    raw_bytes = volume.num_blocks * volume._storage.bytes_per_block
    print(f"# the room: {volume.num_blocks} blocks in {len(tiles)} tiles, {raw_bytes / 2**20:.1f} MiB of compact voxels "
          f"({volume.bytes_per_voxel} B per voxel; was 28)")
    rows = []
    for store_name in ("lmdb", "sqlite"):
        for codec_name in ("zstd", "lz4"):
            codec = make_codec(codec_name)
            with tempfile.TemporaryDirectory() as tmp:
                store = _Lmdb(Path(tmp), codec_name) if store_name == "lmdb" else _Sqlite(Path(tmp))
                t0 = time.perf_counter()
                blobs = {t: encode_tile(codec, c, raw, 8) for t, (c, raw) in tiles.items()}
                encode_s = time.perf_counter() - t0
                t0 = time.perf_counter()
                store.write(blobs)
                write_s = time.perf_counter() - t0
                some = dict(list(blobs.items())[: max(1, len(blobs) // 10)])
                t0 = time.perf_counter()
                store.write(some)
                incr_s = time.perf_counter() - t0
                t0 = time.perf_counter()
                for b in store.read_all():
                    decode_tile(codec, b)
                read_s = time.perf_counter() - t0
                size = store.size()
                if store_name == "lmdb":
                    store.store.close()  # type: ignore[attr-defined]
                else:
                    store.db.close()  # type: ignore[attr-defined]
            rows.append((store_name, codec_name, encode_s, write_s, incr_s, read_s, size))
    base = rows[0]
    print("\n| store | codec | encode s | write all s | write 10 % s | read + decode all s | size MiB | x LMDB+zstd (write, read, size) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:.3f} | {r[3]:.3f} | {r[4]:.3f} | {r[5]:.3f} | {r[6] / 2**20:.2f} | "
              f"{(r[2] + r[3]) / (base[2] + base[3]):.2f}, {r[5] / base[5]:.2f}, {r[6] / base[6]:.2f} |")
    print(f"\ncompression of compact voxels (LMDB+zstd): {raw_bytes / base[6]:.1f}x")

    return 0


if __name__ == "__main__":
    sys.exit(main())
