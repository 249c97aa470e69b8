"""The options of a ``synthetic:key=value,...`` source spec, parsed without building the world.

:func:`synthetic_options` turns the spec's strings into keyword arguments of
:class:`~openfusion.sources.synthetic.SyntheticSource` (plus ``seed``). It imports nothing heavy
(the synthetic package needs Open3D), so :func:`~openfusion.sources.registry.check_source_spec`
can refuse an unknown or malformed option before a command starts anything, with the same message
the source gives when it opens.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

#: spec key -> (keyword of ``SyntheticSource``, converter; None for a 0/1 flag).
SPEC_KEYS: dict[str, tuple[str, Callable[[str], Any] | None]] = {
    "seed": ("seed", int),
    "frames": ("num_frames", int),
    "width": ("width_px", int),
    "height": ("height_px", int),
    "fps": ("fps", float),
    "lap": ("frames_per_lap", int),
    "noise": ("depth_noise", None),
}


def synthetic_options(spec_options: Mapping[str, str]) -> dict[str, Any]:
    """Keyword arguments (``seed``, ``num_frames``, ...) from spec options (strings); ValueError
    naming an unknown key or a value of the wrong type."""
    out: dict[str, Any] = {}
    for key, text in spec_options.items():
        if key not in SPEC_KEYS:
            raise ValueError(f"unknown synthetic option {key!r}; known: {', '.join(sorted(SPEC_KEYS))}")
        name, conv = SPEC_KEYS[key]
        if conv is None:
            if text.lower() not in ("0", "1", "true", "false"):
                raise ValueError(f"synthetic option {key} must be 0/1/true/false, got {text!r}")
            out[name] = text.lower() in ("1", "true")
            continue
        try:
            out[name] = conv(text)
        except ValueError:
            raise ValueError(f"synthetic option {key}={text!r} is not a valid {conv.__name__}") from None
    return out
