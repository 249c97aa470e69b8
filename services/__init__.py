"""Service shells over Zenoh: bridge, geometry, semantic, query."""
