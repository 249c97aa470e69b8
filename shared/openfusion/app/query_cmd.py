"""``openfusion query`` and ``openfusion segment``: ask a running map or a saved one.

    openfusion query "TEXT" [--map ID] [--connect EP] [--top-k K] [--json] [--out FILE.ply]
    openfusion query "TEXT" --map-dir DIR [...]            # a saved map, no services needed
    openfusion query "chair" "table" "lamp" [...]          # several texts at once
    openfusion segment --map-dir DIR --classes "wall,floor,chair" --out seg.ply

Output (stdout carries the answer and nothing else; a successful query writes nothing to stderr
but the one line naming the PLY of ``--out``; ``--verbose`` adds INFO log lines and the libraries'
own output, see :mod:`openfusion.app.quiet`): one block per text, in the order given, each as one
text alone prints it::

    'chair' in minilm-l6-v2:
      key      7  score 0.911  chair     856 points  bbox [2.68, 3.069, 0.01] .. [3.242, 3.56, 0.886]  relevancy 1.00 match
                  near: on floor (key 2), next to table (key 6, 0.04 m)

``score`` is the cosine, ``relevancy`` the LERF relevancy in [0, 1] (with query-side contrast
categories) and ``match`` says the hit is what was asked: the relevancy reaches the embedding
space's calibrated threshold and the hit's margin is at least 0.7 of the text's best in the map
(:mod:`openfusion.mapping.relevancy`, v9);
the second line names up to three nearby regions with the hit's relation to each (``on``,
``under``, ``above``, ``next to``; :mod:`openfusion.mapping.relations`). A text none of whose
regions is a match prints one line instead, and the command still exits 0::

    no match for "zebra" (closest: plant, relevancy 0.01)

A text of the form "X on/under/above/next to Y" ("the chair next to the table", "cup on the
desk") ranks the X regions that stand in the relation to the best Y matches first; the header says
how it was read (``('chair' next to 'table')``) and each such hit names its anchor first
(``next to table (key 6, 0.04 m); near: ...``). (``  no regions`` when the map has no region to
answer). ``--json``: one text prints one object ``{"query", "embedding_space", "regions": [{"key",
"score", "label", "num_points", "bbox_min", "bbox_max", "relevancy", "match", "centroid", "nearby":
[{"key", "label", "relation", "distance_m"}], "relation"?}, ...], "relation"?}`` on one line (the
``relation`` members only for relation queries); several texts print a JSON list of those
objects, in order. Several texts are embedded in one encoder call: against running services in one round trip
(``query/text_batch``, :meth:`~openfusion.client.OpenFusionClient.query_texts`), with
``--map-dir`` by the one encoder. ``--out`` writes the points of every returned region once.

``segment`` writes a binary little-endian PLY of the map's surface points with float ``x y z``
and int ``label`` (index into the class list, -1 where the point has no region).

``query --map-dir`` without ``--out`` reads only the map's dictionary and region summaries
(:func:`openfusion.mapping.mapfile.load_map_summary`, never the volume) and embeds the text with
MiniLM through onnxruntime (no torch import once the model is exported, see
:mod:`openfusion.encoders.text_minilm_onnx`): well under 2 s cold. ``--out`` (points) and maps
saved before summaries were stored (a log line says so) read the whole map. Regions with fewer than
``--min-region-points`` surface points are not answers (the query service's ``min_region_points``).
``--text-encoder`` and ``--min-region-points`` apply to a saved map only (a running map's query
service has its own); the options that find a running map (``--map``, ``--connect``, ``--timeout``,
``--config``, ``--set``, ...) are refused with ``--map-dir``.
``OPENFUSION_QUERY_LEGACY=1`` answers as before all this (whole map, sentence-transformers), for
benchmarks and cross-checks.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from openfusion.app.quiet import quiet_libraries, quiet_onnxruntime
from openfusion.config import add_config_arguments, config_from_args, load_config, setup_logging

logger = logging.getLogger(__name__)

#: ``1``: ``query --map-dir`` reads the whole map and uses sentence-transformers (the old path).
LEGACY_PATH_ENV = "OPENFUSION_QUERY_LEGACY"
#: ``openfusion query --timeout`` when not given: seconds to wait for a running map's services.
DEFAULT_TIMEOUT_S = 10.0


def _load_saved_map(map_dir: Path) -> Any:
    from openfusion.errors import UsageError
    from openfusion.mapping import MapFormatError, load_map
    from openfusion.mapping.mapfile import resolve_map_path

    if not resolve_map_path(map_dir).exists():
        raise UsageError(f"no map at {map_dir} (expected {resolve_map_path(map_dir)}; make one with `openfusion run`)")
    try:
        return load_map(map_dir)
    except MapFormatError as exc:
        raise UsageError(f"cannot read the map at {map_dir}: {exc}") from None


def _load_saved_summary(map_dir: Path) -> Any:
    """The map's dictionary + region summaries; None when it has none (saved before they were
    stored) or cannot be read this way (then :func:`_load_saved_map` reads it or names the problem)."""
    from openfusion.mapping import MapFormatError, load_map_summary
    from openfusion.mapping.mapfile import resolve_map_path

    if not resolve_map_path(map_dir).exists():
        return None
    try:
        summary = load_map_summary(map_dir)
    except MapFormatError:
        return None
    if summary is None:
        logger.warning("the map at %s has no region summaries (saved before they were stored): reading the "
                       "whole map, which is slow; save it again to make queries fast", map_dir)
    return summary


def _answer_saved_map(args: argparse.Namespace, with_points: bool) -> tuple[str, list[list[Any]], list[Any]]:
    """(embedding space, ranked regions of each text, each text's relation query or None) of a
    saved map: from its summaries when they suffice, else from the whole map's surface; every text
    embedded in one encoder call; relevancy with the calibration the map was saved with."""
    from openfusion.errors import UsageError
    from openfusion.mapping.params import default_min_region_points
    from openfusion.mapping.queries import RegionTable, answer_texts, query_regions, subsample_points
    from openfusion.mapping.relevancy import calibration_for

    least = default_min_region_points() if args.min_region_points is None else args.min_region_points
    if least < 1:
        raise UsageError(f"--min-region-points must be >= 1, got {least}")
    up_axis = args.up_axis or "+z"
    legacy = os.environ.get(LEGACY_PATH_ENV, "") == "1"
    summary = None if (with_points or legacy) else _load_saved_summary(args.map_dir)
    if summary is not None:
        space = summary.dictionary.embedding_space
        encoder = _text_encoder_for(space, args.text_encoder)
        answers = answer_texts(summary.dictionary, summary.regions, list(args.text), encoder, top_k=args.top_k,
                               min_points=least, up_axis=up_axis,
                               calibration=calibration_for(space, summary.relevancy))
        return space, [r for r, _ in answers], [a.relation for _, a in answers]
    loaded = _load_saved_map(args.map_dir)
    space = loaded.dictionary.embedding_space
    encoder = _text_encoder_for(space, args.text_encoder, lean=not legacy)
    if legacy:  # as before relevancy and relations: ranked regions only
        vectors = encoder.encode(list(args.text))
        return space, [query_regions(loaded.dictionary, loaded.volume, v, args.top_k, with_points=with_points,
                                     max_points=200_000, min_points=least) for v in vectors], [None] * len(vectors)
    surface = loaded.volume.extract_points()
    table = RegionTable.of_points(surface.keys, surface.points)
    answers = answer_texts(loaded.dictionary, table, list(args.text), encoder, top_k=args.top_k, min_points=least,
                           up_axis=up_axis, calibration=calibration_for(space, loaded.relevancy))
    if with_points:
        for results, _ in answers:
            for res in results:
                res.points = subsample_points(surface.points[surface.keys == res.key], 200_000, seed=res.key)
    return space, [r for r, _ in answers], [a.relation for _, a in answers]


def _text_encoder_for(space: str, name: str | None, *, lean: bool = True) -> Any:
    """The text encoder by name; MiniLM through onnxruntime when ``lean`` (sentence-transformers
    when that is unavailable, logged)."""
    from openfusion.encoders import make_text_encoder
    from openfusion.errors import UsageError

    name = name or "minilm"
    minilm = name.strip().lower() in ("minilm", "gt")
    if (lean and minilm) or name.strip().lower() == "onnx":
        quiet_onnxruntime()  # inside a quiet command only
    encoder = make_text_encoder(name, **({"backend": "onnxruntime"} if lean and minilm else {}))
    if encoder.embedding_space != space:
        raise UsageError(f"the map is in embedding space {space!r} but --text-encoder gives {encoder.embedding_space!r}")
    return encoder


def _answer_record(text: str, space: str, regions: list[Any], relation: Any = None) -> dict[str, Any]:
    from openfusion.app.outputs import region_record

    record: dict[str, Any] = {"query": text, "embedding_space": space, "regions": [region_record(r) for r in regions]}
    if relation is not None:
        record["relation"] = {"target": relation.target, "relation": relation.relation, "anchor": relation.anchor}
    return record


def _print_answers(answers: list[tuple[str, str, list[Any], Any]], *, as_json: bool) -> None:
    """(text, embedding space, regions, relation query or None) of each text: one block per text,
    in order; ``as_json``: one object, or a list of them for several texts. A text none of whose
    regions is a match prints ``no match for "X" (closest: Y, relevancy R)`` as its block."""
    from openfusion.app.outputs import no_match_line, where_line

    records = [_answer_record(text, space, regions, relation) for text, space, regions, relation in answers]
    if as_json:
        print(json.dumps(records[0] if len(records) == 1 else records))
        return
    for (text, _space, regions, relation), record in zip(answers, records, strict=True):
        none = no_match_line(text, regions) if regions else None
        if none is not None:
            print(none)
            continue
        how = f"  ({relation.target!r} {relation.relation} {relation.anchor!r})" if relation is not None else ""
        print(f"{record['query']!r} in {record['embedding_space']}:{how}")
        if not record["regions"]:
            print("  no regions")
        for region, r in zip(regions, record["regions"], strict=True):
            rel = "" if r["relevancy"] is None else f"  relevancy {r['relevancy']:.2f}{' match' if r['match'] else ''}"
            print(f"  key {r['key']:>6}  score {r['score']:.3f}  {r['label'] or '-':<16} {r['num_points']:>7} points  "
                  f"bbox {r['bbox_min']} .. {r['bbox_max']}{rel}")
            where = where_line(region)
            if where:
                print(f"{'':>14}{where}")


def _write_points(path: Path, regions: list[Any]) -> int:
    """The points of ``regions`` (each key once, the first seen) as a PLY with x y z and key."""
    from openfusion.io.ply import write_ply_vertices

    unique = list({int(r.key): r for r in reversed(regions)}.values())[::-1]
    chunks = [(r.points, r.key) for r in unique if r.points is not None and len(r.points)]
    if not chunks:
        return 0
    pts = np.concatenate([c[0] for c in chunks]).astype(np.float32)
    keys = np.concatenate([np.full(len(c[0]), c[1], np.int32) for c in chunks])
    write_ply_vertices(path, {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "key": keys})
    return len(pts)


#: Options of ``openfusion query`` that find a running map: (attribute, flag); refused with --map-dir.
_BUS_OPTIONS = (("config", "--config"), ("map_id", "--map"), ("prefix", "--prefix"),
                ("zenoh_config", "--zenoh-config"), ("mode", "--mode"), ("connect", "--connect"),
                ("listen", "--listen"), ("multicast", "--multicast/--no-multicast"), ("overrides", "--set"),
                ("timeout", "--timeout"))
#: Options of ``openfusion query`` that apply to a saved map only: (attribute, flag).
_SAVED_MAP_OPTIONS = (("text_encoder", "--text-encoder"), ("min_region_points", "--min-region-points"),
                      ("up_axis", "--up-axis"))


def _check_query_options(args: argparse.Namespace) -> None:
    """Refuse values and combinations the query could not honour, before anything is read or joined."""
    from openfusion.errors import UsageError
    from openfusion.wire.limits import check_text, check_top_k

    empty = [i for i, text in enumerate(args.text) if not text.strip()]
    if empty and len(args.text) == 1:
        raise UsageError("the query text is empty")
    if empty:
        raise UsageError(f"query text {empty[0] + 1} of {len(args.text)} is empty")
    # the one set of limits (openfusion.wire.limits), in both modes, before anything is read or joined
    for i, text in enumerate(args.text):
        check_text(text, which=f"text {i + 1} of {len(args.text)} " if len(args.text) > 1 else "")
    check_top_k(args.top_k, name="--top-k")
    if args.map_dir is not None:
        given = [flag for attr, flag in _BUS_OPTIONS if getattr(args, attr, None) not in (None, [])]
        if given:
            raise UsageError(f"{', '.join(given)} {'find' if len(given) > 1 else 'finds'} a running map; --map-dir "
                             "reads a saved one (use one or the other)")
    else:
        given = [flag for attr, flag in _SAVED_MAP_OPTIONS if getattr(args, attr, None) is not None]
        if given:
            raise UsageError(f"{', '.join(given)} {'apply' if len(given) > 1 else 'applies'} to a saved map "
                             "(--map-dir); a running map's query service has its own (set it on that service)")
        if args.timeout is not None and args.timeout <= 0:
            raise UsageError(f"--timeout must be positive, got {args.timeout:g}")
    if args.out is not None and not args.out.parent.is_dir():
        raise UsageError(f"--out: folder {args.out.parent} does not exist")


_OUTPUT_HELP = """\
output (stdout, nothing else; a successful query writes nothing to stderr but the
one line naming the PLY of --out; --verbose adds log lines and the libraries' output):
  one block per TEXT, in order, each as a query of that text alone prints it:
    'chair' in minilm-l6-v2:
      key      7  score 0.911  chair       856 points  bbox [..] .. [..]  relevancy 1.00 match
                  near: on floor (key 2), next to table (key 6, 0.04 m)
    no match for "zebra" (closest: plant, relevancy 0.01)
  score: cosine; relevancy: [0, 1] against the phrases "object", "things", "stuff",
  "texture" and, query side, the categories "animal", "vehicle", "food", "building",
  "landscape", "appliance"; match: what was asked (relevancy reaches the embedding space's
  calibrated threshold and the margin is at least 0.7 of the text's best). A TEXT
  without any match prints the "no match" line (exit status 0).
  "X on|under|above|next to Y" (also: on top of, underneath, beneath, below, over, beside,
  near, by), e.g. "the chair next to the table": X regions in that relation to the best Y
  matches come first, each naming its anchor.
  --json, one TEXT: one object on one line
    {"query": TEXT, "embedding_space": SPACE, "regions": [{"key": INT, "score": FLOAT,
     "label": STR|null, "num_points": INT, "bbox_min": [X, Y, Z], "bbox_max": [X, Y, Z],
     "relevancy": FLOAT|null, "match": BOOL|null, "centroid": [X, Y, Z]|null,
     "nearby": [{"key", "label", "relation", "distance_m"}, ...], "relation"?: {...}}, ...],
     "relation"?: {"target", "relation", "anchor"}}
  --json, several TEXTs: a JSON list of those objects, in the order of the TEXTs
"""


class QueryCommand:
    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        from openfusion.mapping.params import default_min_region_points
        from openfusion.wire.limits import MAX_TEXT_CHARS, MAX_TOP_K

        parser.formatter_class = argparse.RawDescriptionHelpFormatter
        parser.epilog = _OUTPUT_HELP
        parser.add_argument("text", nargs="+", metavar="TEXT",
                            help=f"what to look for, e.g. 'something to sit on' (at most {MAX_TEXT_CHARS} "
                                 "characters); several texts (given together) are answered at once, in one round trip")
        parser.add_argument("--map-dir", type=Path, help="query a saved map folder instead of running services "
                            "(then no option that finds a running map: --map, --connect, --timeout, --config, ...)")
        parser.add_argument("--top-k", type=int, default=5, help=f"regions to return, 1 to {MAX_TOP_K} (default 5)")
        parser.add_argument("--json", action="store_true",
                            help="print JSON: one object for one TEXT, a list of them for several (see below)")
        parser.add_argument("--out", type=Path, help="write the points of the returned regions (of every text, each "
                            "region once) to this PLY")
        parser.add_argument("--verbose", action="store_true",
                            help="show log lines from INFO up (unless --log-level says otherwise) and the "
                                 "libraries' own output (model loading progress, warnings); without it stdout is "
                                 "the answer alone and a successful query writes nothing to stderr")
        parser.add_argument("--text-encoder", help="with --map-dir: text encoder (default: minilm, the gt encoder's "
                            "space); a running map's query service uses its own")
        parser.add_argument("--min-region-points", type=int, metavar="N",
                            help="with --map-dir: regions with fewer surface points are not answers "
                                 f"(default: the query service's min_region_points, {default_min_region_points()})")
        parser.add_argument("--up-axis", choices=("+x", "-x", "+y", "-y", "+z", "-z"),
                            help="with --map-dir: the map's up axis for relations (default +z, the synthetic "
                                 "world's and ScanNet's; the query service's up_axis)")
        parser.add_argument("--timeout", type=float, default=None,
                            help=f"seconds to wait for the services (default {DEFAULT_TIMEOUT_S:g})")
        add_config_arguments(parser)

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        _check_query_options(args)
        with quiet_libraries(not args.verbose):
            answers = _answer(args)
        _print_answers(answers, as_json=args.json)
        if args.out is not None:
            n = _write_points(args.out, [r for _text, _space, regions, _rel in answers for r in regions])
            print(f"wrote {n} points to {args.out}", file=sys.stderr)
        return 0


def _answer(args: argparse.Namespace) -> list[tuple[str, str, list[Any], Any]]:
    """(text, embedding space, ranked regions) of each text, in order, from a saved map or running
    services."""
    texts = list(args.text)
    with_points = args.out is not None
    verbose_level = "INFO" if args.verbose else "WARNING"
    if args.map_dir is not None:
        if args.log_level or args.verbose:  # validated as the config would (no bus options here)
            setup_logging(load_config(cli={"log_level": args.log_level or verbose_level}, environ={}).log_level)
        space, answers, relations = _answer_saved_map(args, with_points)
        return [(text, space, regions, relation)
                for text, regions, relation in zip(texts, answers, relations, strict=True)]
    from openfusion.bus import QueryError
    from openfusion.client import OpenFusionClient
    from openfusion.wire.limits import LimitError

    config = config_from_args(args)
    setup_logging(config.log_level if args.log_level else verbose_level)
    timeout_s = DEFAULT_TIMEOUT_S if args.timeout is None else args.timeout
    with OpenFusionClient.from_config(config, timeout_s=timeout_s) as client:
        try:
            if len(texts) == 1:  # the one-text endpoint, as always (query services without batches answer it)
                replies = [client.query_text(texts[0], top_k=args.top_k, with_points=with_points)]
            else:  # one round trip (up to 64 texts)
                replies = client.query_texts(texts, top_k=args.top_k, with_points=with_points)
        except QueryError as exc:
            if exc.code == "too_large":  # a limit the service holds (an older one may hold others): the user's to fix
                raise LimitError(exc.reason) from None
            raise
    return [(text, reply.embedding_space, reply.regions, reply.relation)
            for text, reply in zip(texts, replies, strict=True)]


class SegmentCommand:
    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--map-dir", type=Path, required=True, help="a saved map folder")
        parser.add_argument("--classes", required=True, help="comma-separated class names, e.g. 'wall,floor,chair'")
        parser.add_argument("--out", type=Path, required=True, help="output PLY (x y z float, label int)")
        parser.add_argument("--text-encoder", help="text encoder (default minilm)")

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        from openfusion.errors import UsageError
        from openfusion.io.ply import write_ply_vertices
        from openfusion.mapping import segment_points

        classes = [c.strip() for c in args.classes.split(",") if c.strip()]
        if not classes:
            raise UsageError("--classes needs at least one class name")
        if not args.out.parent.is_dir():
            raise UsageError(f"--out: folder {args.out.parent} does not exist")
        loaded = _load_saved_map(args.map_dir)
        encoder = _text_encoder_for(loaded.dictionary.embedding_space, args.text_encoder)
        points, labels = segment_points(loaded.volume, loaded.dictionary, encoder.encode(classes))
        write_ply_vertices(args.out, {"x": points[:, 0].astype(np.float32), "y": points[:, 1].astype(np.float32),
                                      "z": points[:, 2].astype(np.float32), "label": labels.astype(np.int32)})
        counts = {name: int((labels == i).sum()) for i, name in enumerate(classes)}
        counts["(none)"] = int((labels < 0).sum())
        print(json.dumps({"points": int(len(points)), "classes": counts, "out": str(args.out)}))
        return 0
