"""Third-party files the query page serves, vendored at pinned versions (package data, no code)."""
