"""Named transfer functions, one registry for every interface: a scene's `"tf": "ct-bone"` (Python, HTTP, jobs,
CLI), `lodcast render --tf ct-bone`, `lodcast presets` and `GET /presets`. Besides these fixed ones (CT, in
Hounsfield units), adaptive presets ("auto", "mr-soft") place a template on each volume's α-histogram peaks, for
data without a fixed scale such as MR (renderer/scene/adaptive_tf.py). Plain data: the scene model resolves a
name through `preset()` before validating the TF."""
from __future__ import annotations

import copy
from typing import Any

__all__ = ["PRESETS", "ADAPTIVE", "preset", "preset_names", "catalogue"]

# Transfer functions for CT in Hounsfield units (`lodcast render --tf ct-bone`): bone, the thin skin band between
# air and fat, and both; the LOD benchmarks and tests measure with these.
PRESETS: dict[str, dict] = {
    "ct-bone": {"points": [{"value": 250, "color": [0.9, 0.85, 0.75], "opacity": 0.0},
                           {"value": 700, "color": [1.0, 1.0, 0.95], "opacity": 0.6},
                           {"value": 1500, "color": [1.0, 1.0, 1.0], "opacity": 0.9}]},
    "ct-skin": {"points": [{"value": -600, "color": [0.9, 0.6, 0.5], "opacity": 0.0},
                           {"value": -400, "color": [0.9, 0.7, 0.6], "opacity": 0.3},
                           {"value": -200, "color": [0.9, 0.7, 0.6], "opacity": 0.0}]},
    # translucent skin and opaque bone, with air, fat and the gap to bone transparent
    "ct-skin-bone": {"points": [{"value": -600, "color": [0.9, 0.6, 0.5], "opacity": 0.0},
                                {"value": -300, "color": [0.9, 0.7, 0.6], "opacity": 0.25},
                                {"value": 100, "color": [0.8, 0.3, 0.3], "opacity": 0.0},
                                {"value": 300, "color": [1.0, 1.0, 0.9], "opacity": 0.0},
                                {"value": 900, "color": [1.0, 1.0, 1.0], "opacity": 0.9}]},
    # for dual-TF compositing (a scene's tf2 over its tf, "X-ray vision"): an opaque body surface to look into,
    # the densest bone, calcifications and iodine contrast (a narrow band above ordinary bone), and metal
    # (implants, bullets and fragments, dental fillings: above any tissue)
    "ct-body": {"points": [{"value": -500, "color": [0.9, 0.65, 0.55], "opacity": 0.0},
                           {"value": -200, "color": [0.9, 0.7, 0.6], "opacity": 0.5},
                           {"value": 300, "color": [0.9, 0.7, 0.6], "opacity": 0.5}]},
    "ct-dense": {"points": [{"value": 1300, "color": [1.0, 0.3, 0.2], "opacity": 0.0},
                            {"value": 1450, "color": [1.0, 0.3, 0.2], "opacity": 0.9}]},
    "ct-metal": {"points": [{"value": 2500, "color": [0.3, 0.6, 1.0], "opacity": 0.0},
                            {"value": 3000, "color": [0.6, 0.85, 1.0], "opacity": 1.0}]},
}


# Adaptive presets (renderer/scene/adaptive_tf.py places them on a volume's α-histogram peaks).
#: template: (u, colour, opacity) control points, u = 0 the background peak and u = 1 the tissue peak; values
#: beyond the volume's range are clipped to it
ADAPTIVE: dict[str, dict[str, Any]] = {
    "auto": {
        "description": "the object's surface: transparent up to halfway between the background and the tissue "
                       "peaks of the α-histogram, opaque from the tissue peak up (CT or MR; lit if shading is on)",
        "points": [(0.5, (0.85, 0.55, 0.45), 0.0), (1.0, (0.95, 0.8, 0.7), 0.6), (2.5, (1.0, 1.0, 0.95), 0.9)],
    },
    "mr-soft": {
        "description": "MR: translucent tissue around the α-histogram's tissue peak, brighter structures (fat, "
                       "vessels with contrast) more opaque; the head's inside stays visible",
        "points": [(0.55, (0.8, 0.4, 0.3), 0.0), (1.0, (0.9, 0.6, 0.45), 0.008), (1.6, (1.0, 0.85, 0.7), 0.03),
                   (3.0, (1.0, 1.0, 0.95), 0.1)],
    },
}



def preset_names() -> list[str]:
    """Fixed presets and the adaptive ones (renderer/scene/adaptive_tf.py: placed on each volume's histogram)."""
    return sorted([*PRESETS, *ADAPTIVE])


def catalogue() -> dict[str, dict]:
    """Every preset as `GET /presets` and `lodcast presets --json` list it: a fixed one as its TF JSON, an adaptive
    one as {"template": name, "description": ...}."""
    return {**copy.deepcopy(PRESETS),
            **{name: {"template": name, "description": t["description"]} for name, t in ADAPTIVE.items()}}


def preset(name: str) -> dict:
    """A copy of the preset's TF JSON (an adaptive preset: its template); KeyError naming the known presets."""
    if name in ADAPTIVE:
        return {"template": name}
    try:
        return copy.deepcopy(PRESETS[name])
    except KeyError:
        raise KeyError(f"unknown preset {name!r}; known: {', '.join(preset_names())}") from None
