"""Image output: straight-alpha 8-bit PNG (Pillow) or the float32 premultiplied RGBA itself (.npy)."""
from __future__ import annotations

import io
import json
import os
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np

from lodcast.errors import LodcastError
from lodcast.renderer.image.report import RenderReport

__all__ = ["RenderResult", "ImageError", "to_straight_rgba8", "png_bytes", "save_image", "format_for"]


class ImageError(LodcastError, ValueError):
    """Unsupported output format or unwritable destination."""


#: the formats an image is written in, by the names (extensions) that ask for them: 8-bit sRGB images (PNG, WebP
#: and TIFF with straight alpha; JPEG, which has no alpha, composited over opaque black) and the float32
#: premultiplied RGBA itself (.npy)
IMAGE_FORMATS = {"png": "png", "jpg": "jpg", "jpeg": "jpg", "webp": "webp", "tif": "tif", "tiff": "tif", "npy": "npy"}
_SUFFIXES = ".png, .jpg (.jpeg), .webp, .tif (.tiff) or .npy"


def format_for(path: str | Path, format: str | None = None) -> str:
    """The format `path` is written in (png, jpg, webp, tif or npy), from `format` or else its extension; ImageError
    naming the suffixes it takes otherwise."""
    ext = Path(path).suffix.lower().lstrip(".")
    fmt = IMAGE_FORMATS.get((format or ext).lower().lstrip("."))
    if fmt is None and format:
        raise ImageError(f"output {str(path)!r}: format must be one of {', '.join(sorted(set(IMAGE_FORMATS.values())))}, "
                         f"got {format!r}")
    if fmt is None:
        raise ImageError(f"output {str(path)!r}: the name must end in {_SUFFIXES}, got "
                         f"{'.' + ext if ext else 'no extension'}")
    if format and ext in IMAGE_FORMATS and IMAGE_FORMATS[ext] != fmt:
        raise ImageError(f"output {str(path)!r}: extension .{ext} contradicts format {fmt!r}")
    return fmt


def to_straight_rgba8(rgba: np.ndarray) -> np.ndarray:
    """Premultiplied float RGBA -> straight-alpha uint8 (colour = C / A where A > 0, rounded to nearest)."""
    rgba = np.asarray(rgba)
    # one float64 buffer worked in place: every interactive frame pays for this conversion before its PNG
    out = np.empty(rgba.shape, np.float64)
    alpha = out[..., 3]
    np.clip(rgba[..., 3], 0.0, 1.0, out=alpha)
    out[..., :3] = 0.0
    np.divide(rgba[..., :3], alpha[..., None], out=out[..., :3], where=(alpha > 0)[..., None])
    np.clip(out, 0.0, 1.0, out=out)
    np.nan_to_num(out, copy=False)
    out *= 255.0
    np.rint(out, out=out)
    return out.astype(np.uint8)


def png_bytes(rgba: np.ndarray, text: dict[str, Any] | None = None) -> bytes:
    """The 8-bit PNG, tagged sRGB (the colours are sRGB as the TF gives them), with `text` (e.g. the scene and
    the report, as JSON) in iTXt chunks named lodcast:KEY: a picture says how it was made."""
    from PIL import Image, PngImagePlugin

    info = PngImagePlugin.PngInfo()
    info.add(b"sRGB", b"\x00")  # rendering intent: perceptual
    for key, value in (text or {}).items():
        info.add_itxt(f"lodcast:{key}", value if isinstance(value, str) else json.dumps(value, default=str))
    buf = io.BytesIO()
    # zlib's fastest level, matching runs only: an interactive frame over HTTP waits for its encoding, which
    # Pillow's default level makes several times longer for files only somewhat smaller; after PNG's row filters a
    # rendered image is mostly runs, which Z_RLE finds faster than the default strategy, in files about as small
    Image.fromarray(to_straight_rgba8(rgba), mode="RGBA").save(buf, format="PNG", pnginfo=info, compress_level=1,
                                                               compress_type=zlib.Z_RLE)
    return buf.getvalue()


def save_image(path: str | Path, rgba: np.ndarray, format: str | None = None,
               text: dict[str, Any] | None = None) -> Path:
    """Write atomically (temporary name, then rename): nothing is half-written. The format follows `format`, else
    the extension (format_for): .npy the float32 premultiplied RGBA as given; .png, .webp (lossless) and .tif 8-bit
    straight alpha; .jpg (no alpha) 8-bit composited over opaque black, which leaves an image rendered over an
    opaque background as it is. `text`: PNG text (png_bytes)."""
    path = Path(path)
    fmt = format_for(path, format)
    if not path.parent.is_dir():
        raise ImageError(f"output {str(path)!r}: folder {str(path.parent)!r} does not exist")
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        if fmt == "npy":
            with open(tmp, "wb") as f:
                np.save(f, np.ascontiguousarray(rgba, dtype=np.float32))
        elif fmt == "png":
            tmp.write_bytes(png_bytes(rgba, text))
        else:
            from PIL import Image

            if fmt == "jpg":  # premultiplied colour is the image over opaque black
                rgb = np.round(np.clip(np.nan_to_num(np.asarray(rgba, np.float64)[..., :3]), 0.0, 1.0) * 255.0)
                Image.fromarray(rgb.astype(np.uint8), mode="RGB").save(tmp, format="JPEG", quality=95, subsampling=0)
            else:
                image = Image.fromarray(to_straight_rgba8(rgba), mode="RGBA")
                if fmt == "webp":
                    image.save(tmp, format="WEBP", lossless=True)
                else:
                    image.save(tmp, format="TIFF", compression="tiff_adobe_deflate")
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise ImageError(f"output {str(path)!r}: {exc.strerror or exc}") from None
    return path


@dataclass(frozen=True)
class RenderResult:
    """`rgba`: float32 premultiplied RGBA, shape (H, W, 4), row 0 at the top; `report`: what the render did, a
    JSON-ready dict (typed `RenderReport`: every key and its meaning in docs/reference.md)."""

    rgba: np.ndarray
    report: RenderReport = field(default_factory=lambda: cast(RenderReport, {}))
    scene: dict | None = None  # the scene as rendered (JSON), stored in the PNG beside the report

    def _text(self) -> dict:
        return {k: v for k, v in (("scene", self.scene), ("report", self.report)) if v}

    def save(self, path: str | Path, format: str | None = None) -> Path:
        return save_image(path, self.rgba, format, self._text())

    def png_bytes(self) -> bytes:
        return png_bytes(self.rgba, self._text())

    def _repr_png_(self) -> bytes:  # notebooks show the picture
        return self.png_bytes()
