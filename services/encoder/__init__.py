"""encoder: a stateless region-encoder worker of the encoder pool."""
