"""three.js r170, vendored unchanged (see README.md here; package data, no code)."""
