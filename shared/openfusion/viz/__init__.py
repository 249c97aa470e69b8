"""Seeing the map: pictures, files and live views of a semantic map (docs/VISUALISE.md).

Modules (import what you need; this package imports nothing heavy by itself):

- :mod:`openfusion.viz.picture`: ``open_map``, ``picture_of_map`` (a PNG-ready picture of a saved
  map, optionally with a text query highlighted), ``colour_mesh``.
- :mod:`openfusion.viz.render`: ``render_mesh`` (headless CPU ray casting with Lambert shading and
  doll's-house visibility), ``draw_caption``, ``save_png``.
- :mod:`openfusion.viz.camera`: ``overview_camera`` (above and outside the map, fitted to it).
- :mod:`openfusion.viz.colouring` / :mod:`openfusion.viz.palette`: colour modes (camera colour,
  region key, label, query highlight) with legends, deterministic palette.
- :mod:`openfusion.viz.export`: PLY (mesh / points) and GLB (trimesh) files plus legend files.
- :mod:`openfusion.viz.query`: the text encoder of a map's embedding space; ranked matches.
- :mod:`openfusion.viz.rerun_log`: ``RerunLogger`` (rerun-sdk) with ``save:``/``spawn``/``serve``.
- :mod:`openfusion.app.render_cmd` / :mod:`openfusion.app.export_cmd`: ``openfusion render`` / ``openfusion export``.
- :mod:`openfusion.testing.maps`: tiny synthetic maps and ground-truth projections for tests.
"""
