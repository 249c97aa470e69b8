"""openfusion.testing."""
