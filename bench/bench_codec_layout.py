#!/usr/bin/env python3
"""Tile blob layouts of the tile store, measured on a walk through the synthetic building: format 1
(every attribute of every voxel, byte-shuffled, zstd) against format 2 (the default since issue 33's
map-size work: an unobserved voxel's TSDF and colour left out, observed free-space voxels' TSDF
of exactly 1.0 as one bit each), in one run on the same tiles; and each layout at zstd levels 3,
6 (the store's) and 9. Lossless both: every tile is decoded and compared.

Prints one table: MB of tiles, MB per m^2 of floor (the issue's target is 0.3 for the map on disk,
which adds the store's pages), encode and decode seconds, and size / time against format 1 at the
store's level.

    .venv/bin/python bench/bench_codec_layout.py --quick   # 4 rooms, 30 frames per room, 320x240 (default)
    .venv/bin/python bench/bench_codec_layout.py --full    # 10 rooms
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def main(argv: list[str] | None = None) -> int:
    from openfusion.mapping.tilecodec import _Zstd as Zstd  # the store's codec, at other levels too
    from openfusion.mapping.tilecodec import decode_tile, encode_tile
    from openfusion.sources import open_source
    from openfusion.testing.maps import volume_with_every_tile

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="4 rooms (default)")
    size.add_argument("--full", action="store_true", help="10 rooms")
    args = parser.parse_args(argv)
    rooms = 10 if args.full else 4
    spec = f"synthetic:building,rooms={rooms},frames={rooms * 30},width=320,height=240"
    source = open_source(spec)
    meta = source.metadata() if callable(source.metadata) else source.metadata  # type: ignore[attr-defined]
    floor_m2 = float(meta["floor_area_m2"])
    volume, tiles = volume_with_every_tile(source)
    res = volume.params.block_resolution
    print(f"# {rooms} rooms, {floor_m2:.0f} m^2 of floor: {volume.num_blocks} blocks in {len(tiles)} tiles "
          f"({volume.num_blocks * 8192 / 1e6:.0f} MB of compact voxels)")
    rows = []
    for level in (3, 6, 9):
        codec = Zstd(level)
        for dense in (True, False):
            t0 = time.perf_counter()
            blobs = {t: encode_tile(codec, c, raw, res, dense=dense) for t, (c, raw) in tiles.items()}
            enc = time.perf_counter() - t0
            t0 = time.perf_counter()
            decoded = {t: decode_tile(codec, b) for t, b in blobs.items()}
            dec = time.perf_counter() - t0
            for t, (c, raw) in tiles.items():  # lossless: every value back
                np.testing.assert_array_equal(decoded[t][0], c)
                for k in raw:
                    np.testing.assert_array_equal(decoded[t][1][k], raw[k])
            rows.append((level, "1 (dense)" if dense else "2 (observed)", sum(len(b) for b in blobs.values()) / 1e6, enc, dec))
    base = next(r for r in rows if r[0] == 6 and r[1].startswith("1"))
    print("\n| zstd level | blob format | tiles MB | MB per m^2 | encode s | decode s | size x format 1 @6 | encode x |")
    print("|---|---|---|---|---|---|---|---|")
    for level, name, mb, enc, dec in rows:
        print(f"| {level} | {name} | {mb:.2f} | {mb / floor_m2:.4f} | {enc:.2f} | {dec:.2f} | {mb / base[2]:.3f} | {enc / base[3]:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
