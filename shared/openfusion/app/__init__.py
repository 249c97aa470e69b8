"""openfusion.app."""
