"""Image output: straight-alpha 8-bit PNG (Pillow) or the float32 premultiplied RGBA itself (.npy)."""
from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lodcast.errors import LodcastError

__all__ = ["RenderResult", "ImageError", "to_straight_rgba8", "png_bytes", "save_image", "format_for"]


class ImageError(LodcastError, ValueError):
    """Unsupported output format or unwritable destination."""


def format_for(path: str | Path, format: str | None = None) -> str:
    ext = Path(path).suffix.lower().lstrip(".")
    fmt = (format or ext).lower()
    if fmt not in ("png", "npy"):
        raise ImageError(f"output {str(path)!r}: format must be png or npy (from the extension or --format), got {fmt or 'none'!r}")
    if format and ext and ext in ("png", "npy") and ext != fmt:
        raise ImageError(f"output {str(path)!r}: extension .{ext} contradicts format {fmt!r}")
    return fmt


def to_straight_rgba8(rgba: np.ndarray) -> np.ndarray:
    """Premultiplied float RGBA -> straight-alpha uint8 (colour = C / A where A > 0, rounded to nearest)."""
    a = np.clip(rgba[..., 3:4].astype(np.float64), 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(a > 0, rgba[..., :3] / np.where(a > 0, a, 1.0), 0.0)
    out = np.concatenate([np.clip(c, 0.0, 1.0), a], axis=-1)
    return np.round(np.nan_to_num(out) * 255.0).astype(np.uint8)


def png_bytes(rgba: np.ndarray, text: dict[str, Any] | None = None) -> bytes:
    """The 8-bit PNG, tagged sRGB (the colours are sRGB as the TF gives them), with `text` (e.g. the scene and
    the report, as JSON) in iTXt chunks named lodcast:KEY: a picture says how it was made."""
    from PIL import Image, PngImagePlugin

    info = PngImagePlugin.PngInfo()
    info.add(b"sRGB", b"\x00")  # rendering intent: perceptual
    for key, value in (text or {}).items():
        info.add_itxt(f"lodcast:{key}", value if isinstance(value, str) else json.dumps(value, default=str))
    buf = io.BytesIO()
    Image.fromarray(to_straight_rgba8(rgba), mode="RGBA").save(buf, format="PNG", pnginfo=info)
    return buf.getvalue()


def save_image(path: str | Path, rgba: np.ndarray, format: str | None = None,
               text: dict[str, Any] | None = None) -> Path:
    """Write atomically (temporary name, then rename): nothing is half-written. `text`: PNG text (png_bytes)."""
    path = Path(path)
    fmt = format_for(path, format)
    if not path.parent.is_dir():
        raise ImageError(f"output {str(path)!r}: folder {str(path.parent)!r} does not exist")
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        if fmt == "npy":
            with open(tmp, "wb") as f:
                np.save(f, np.ascontiguousarray(rgba, dtype=np.float32))
        else:
            tmp.write_bytes(png_bytes(rgba, text))
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise ImageError(f"output {str(path)!r}: {exc.strerror or exc}") from None
    return path


@dataclass(frozen=True)
class RenderResult:
    """`rgba`: float32 premultiplied RGBA, shape (H, W, 4), row 0 at the top; `report`: JSON-ready dict."""

    rgba: np.ndarray
    report: dict = field(default_factory=dict)
    scene: dict | None = None  # the scene as rendered (JSON), stored in the PNG beside the report

    def _text(self) -> dict:
        return {k: v for k, v in (("scene", self.scene), ("report", self.report)) if v}

    def save(self, path: str | Path, format: str | None = None) -> Path:
        return save_image(path, self.rgba, format, self._text())

    def png_bytes(self) -> bytes:
        return png_bytes(self.rgba, self._text())

    def _repr_png_(self) -> bytes:  # notebooks show the picture
        return self.png_bytes()
