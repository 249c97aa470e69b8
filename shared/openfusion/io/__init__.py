"""openfusion.io."""
