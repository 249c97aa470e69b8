"""openfusion.wire."""
