"""napari reader plugin (npe2; manifest store/napari.yaml, entry point in pyproject.toml): a lodcast store opens
as one multiscale image layer with its levels, world scale and translation, and the contrast window of its OME
`omero` metadata (a CT in the soft-tissue window). napari itself is optional (`pip install "lodcast[napari]"`);
nothing here imports it."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

__all__ = ["napari_get_reader", "read_store"]


def napari_get_reader(path: str | list[str]) -> Callable[[Any], list[tuple[Any, dict[str, Any], str]]] | None:
    """The reader for `path` when it is a lodcast store (a folder whose root zarr.json marks one), else None, so
    that napari offers other readers."""
    if isinstance(path, list):
        if len(path) != 1:
            return None
        path = path[0]
    p = Path(str(path))
    if not (p / "zarr.json").is_file():
        return None
    try:
        text = (p / "zarr.json").read_text()
    except OSError:
        return None
    return read_store if '"lodcast"' in text else None


def read_store(path: str | list[str]) -> list[tuple[Any, dict[str, Any], str]]:
    """[(levels, layer keywords, "image")]: the level arrays (lazy zarr arrays, finest first), scale and
    translate of level 0 in world units (napari derives the coarser levels' from their shapes), the contrast
    limits of the store's omero window, the units and the store's attributes as metadata."""
    from lodcast.store.store import open_store

    store = open_store(path[0] if isinstance(path, list) else path)
    levels = [store.level(k) for k in range(store.n_levels) if min(store.layout.level_shape(k)) >= 1]
    window = ((store.attrs.get("ome") or {}).get("omero") or {}).get("channels", [{}])[0].get("window") or {}
    lo, hi = store.value_range
    limits = (float(window.get("start", lo)), float(window.get("end", hi if hi > lo else lo + 1.0)))
    kwargs: dict[str, Any] = {
        "name": store.name,
        "multiscale": True,
        "scale": list(store.spacing),
        "translate": list(store.origin),
        "contrast_limits": list(limits),
        "units": store.units,
        "metadata": {"lodcast": {"location": store.location, "orientation": store.orientation,
                                 "value_range": [lo, hi]}},
    }
    return [(levels, kwargs, "image")]
