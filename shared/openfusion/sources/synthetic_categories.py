"""The synthetic world's categories and their base colours, without building the world.

:data:`CATEGORIES` is every raw category name the built-in scene can contain. It lives here, not
in ``openfusion.sources.synthetic`` (which needs Open3D), so a process that only needs the names
(an encoder worker embedding them before it announces itself) imports nothing heavy.
"""

from __future__ import annotations

# Base colors per category (RGB 0..1); instances jitter around them.
PALETTE: dict[str, tuple[float, float, float]] = {
    "wall": (0.86, 0.84, 0.78),
    "floor": (0.62, 0.45, 0.30),
    "ceiling": (0.93, 0.93, 0.92),
    "door": (0.55, 0.38, 0.22),
    "window": (0.70, 0.85, 0.95),
    "picture": (0.25, 0.20, 0.15),
    "bed": (0.45, 0.30, 0.20),
    "pillow": (0.90, 0.90, 0.95),
    "sofa": (0.25, 0.35, 0.55),
    "bookshelf": (0.50, 0.35, 0.20),
    "cabinet": (0.80, 0.78, 0.70),
    "desk": (0.70, 0.55, 0.35),
    "monitor": (0.08, 0.08, 0.10),
    "office chair": (0.15, 0.15, 0.18),
    "table": (0.60, 0.42, 0.25),
    "chair": (0.75, 0.20, 0.15),
    "lamp": (0.95, 0.85, 0.55),
    "plant": (0.20, 0.55, 0.20),
    "trash can": (0.35, 0.40, 0.45),
}

CATEGORIES: tuple[str, ...] = tuple(PALETTE)
"""Every raw category the synthetic world can contain (walls/floor/ceiling included)."""
