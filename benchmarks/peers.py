"""VTK's CPU ray caster (vtkFixedPointVolumeRayCastMapper) set up to render what lodcast renders, for `run.py`.

Conventions matched to lodcast's (docs/reference.md; each one changes the image measurably if left at VTK's default):
* the box: VTK's volume ends at the outer voxel centres, lodcast's half a voxel further out (the field clamped to
  the edge value). The volume is padded by one edge-replicated voxel on each side and clipped to lodcast's box
  with six clipping planes;
* opacity per unit length: ScalarOpacityUnitDistance = the smallest spacing (lodcast's default `unit_distance`);
* the step: SampleDistance = step × the smallest spacing, with AutoAdjustSampleDistances and
  LockSampleDistanceToInputSpacing off, and one ray per pixel (ImageSampleDistance 1);
* colour: piecewise linear in RGB, trilinear interpolation, no shading;
* the camera: lodcast's orbit camera as a look-at (eye, target, up) with the same vertical field of view;
* the image: FixedPoint's own ray-cast image (15-bit fixed point, premultiplied, bottom-up), read before the
  render window resamples it onto the screen by half a pixel, flipped to top-down and scaled to [0, 1].
It needs an OpenGL context for the render window (EGL or OSMesa offscreen, or X); `available()` says why not.

VTK's GPU ray caster (vtkOpenGLGPUVolumeRayCastMapper, `GpuRayCast`) gets the same set-up where an OpenGL context
can be had; its image is the window's RGBA (premultiplied over a transparent black background, 8 bits per channel,
bottom-up) read back as floats. `renderer_name()` says what runs it: on a machine without a GPU, Mesa's llvmpipe,
which runs the GPU mapper's shaders on the CPU cores.
"""
from __future__ import annotations

import ctypes
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from reference import box_bounds, orbit_to_lookat  # noqa: E402

__all__ = ["available", "renderer_name", "FixedPoint", "GpuRayCast"]

FP_SCALE = 32767.0  # VTKKW_FP_SCALE: FixedPoint's 1.0


def available() -> str | None:
    """None when VTK can render offscreen here, else the reason."""
    if not os.environ.get("DISPLAY"):  # VTK would try X first and log a warning before falling back to EGL
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    try:
        import vtk
    except ImportError as e:
        return f"VTK is not installed ({e}; pip install vtk)"
    try:
        w = vtk.vtkRenderWindow()
        w.SetOffScreenRendering(1)
        w.SetSize(8, 8)
        w.Render()
        w.Finalize()
    except Exception as e:  # noqa: BLE001 - any failure to get a context means no peer
        return f"VTK cannot open an offscreen OpenGL context ({e})"
    return None


def _vtk_array(vol: np.ndarray):
    from vtk.util import numpy_support

    return numpy_support.numpy_to_vtk(np.ascontiguousarray(vol).reshape(-1), deep=True,
                                      array_type=numpy_support.get_vtk_array_type(vol.dtype))


def renderer_name() -> str:
    """The OpenGL renderer VTK's windows get here (e.g. "llvmpipe (LLVM 15.0.6, 256 bits)")."""
    import vtk

    w = vtk.vtkRenderWindow()
    w.SetOffScreenRendering(1)
    w.SetSize(8, 8)
    w.Render()
    caps = w.ReportCapabilities() or ""
    w.Finalize()
    for line in caps.splitlines():
        if line.startswith("OpenGL renderer string:"):
            return line.split(":", 1)[1].strip()
    return "unknown"


class _VtkPeer:
    """One volume in one render window, with lodcast's conventions (module doc); `render(scene, step)` returns
    (premultiplied RGBA top-down, seconds)."""

    name = ""

    def _mapper(self, threads: int) -> Any:
        raise NotImplementedError

    def _image(self, W: int, H: int) -> np.ndarray:
        raise NotImplementedError

    def __init__(self, vol: np.ndarray, spacing, origin, threads: int = 2):
        import vtk

        self.vtk = vtk
        self.shape, self.spacing, self.origin = vol.shape, tuple(spacing), tuple(origin)
        padded = np.pad(vol, 1, mode="edge")
        img = vtk.vtkImageData()
        img.SetDimensions(*padded.shape[::-1])
        sp_xyz = np.asarray(spacing, np.float64)[::-1]
        img.SetSpacing(*sp_xyz)
        img.SetOrigin(*(np.asarray(origin, np.float64)[::-1] - sp_xyz))
        img.GetPointData().SetScalars(_vtk_array(padded))
        self.mapper = m = self._mapper(threads)
        m.SetInputData(img)
        m.SetAutoAdjustSampleDistances(0)
        m.SetLockSampleDistanceToInputSpacing(0)
        m.SetImageSampleDistance(1.0)
        lo, hi = box_bounds(vol.shape, spacing, origin)
        for axis in range(3):
            for corner, sign in ((lo, 1.0), (hi, -1.0)):  # VTK keeps the side a plane's normal points to
                p = vtk.vtkPlane()
                n = [0.0, 0.0, 0.0]
                n[axis] = sign
                p.SetOrigin(*corner)
                p.SetNormal(*n)
                m.AddClippingPlane(p)
        self.prop = vtk.vtkVolumeProperty()
        self.prop.SetInterpolationTypeToLinear()
        self.prop.ShadeOff()
        self.prop.SetScalarOpacityUnitDistance(float(min(spacing)))
        self.volume = vtk.vtkVolume()
        self.volume.SetMapper(m)
        self.volume.SetProperty(self.prop)
        self.renderer = vtk.vtkRenderer()
        self.renderer.SetBackground(0, 0, 0)
        self.renderer.AddVolume(self.volume)
        self.renderer.SetBackgroundAlpha(0.0)
        self.window = vtk.vtkRenderWindow()
        self.window.SetOffScreenRendering(1)
        self.window.SetAlphaBitPlanes(1)
        self.window.AddRenderer(self.renderer)
        self._tf_key = None

    def _set_tf(self, tf: dict[str, Any]) -> None:
        key = repr(tf)
        if key == self._tf_key:
            return
        vtk = self.vtk
        op, col = vtk.vtkPiecewiseFunction(), vtk.vtkColorTransferFunction()
        col.SetColorSpaceToRGB()
        for p in sorted(tf["points"], key=lambda p: float(p["value"])):
            op.AddPoint(float(p["value"]), float(p["opacity"]))
            col.AddRGBPoint(float(p["value"]), *map(float, p["color"]))
        op.SetClamping(1)
        col.SetClamping(1)
        self.prop.SetScalarOpacity(op)
        self.prop.SetColor(col)
        self._tf_key = key

    def render(self, scene: dict[str, Any], step: float) -> tuple[np.ndarray, float]:
        W, H = int(scene["width"]), int(scene["height"])
        self._set_tf(scene["tf"])
        self.mapper.SetSampleDistance(step * float(min(self.spacing)))
        cam = orbit_to_lookat(scene["camera"], self.shape, self.spacing, self.origin, W / H)
        c = self.renderer.GetActiveCamera()
        c.SetPosition(*cam["eye"])
        c.SetFocalPoint(*cam["target"])
        c.SetViewUp(*cam["up"])
        c.SetViewAngle(float(cam.get("fov", 30.0)))
        self.window.SetSize(W, H)
        self.renderer.ResetCameraClippingRange()
        t = time.perf_counter()
        self.window.Render()
        img = self._image(W, H)  # timed with it: lodcast's wall time ends with the image on the host too
        return img, time.perf_counter() - t

    def close(self) -> None:
        self.window.Finalize()


class FixedPoint(_VtkPeer):
    """vtkFixedPointVolumeRayCastMapper on `threads` CPU threads; its own 15-bit ray-cast image."""

    name = "VTK FixedPoint"

    def _mapper(self, threads: int) -> Any:
        m = self.vtk.vtkFixedPointVolumeRayCastMapper()
        m.SetNumberOfThreads(threads)
        return m

    def _image(self, W: int, H: int) -> np.ndarray:
        ri = self.mapper.GetRayCastImage()
        mw, mh = ri.GetImageMemorySize()
        uw, uh = ri.GetImageInUseSize()
        ox, oy = ri.GetImageOrigin()
        vw, vh = ri.GetImageViewportSize()
        assert (vw, vh) == (W, H), f"FixedPoint's viewport {vw}x{vh} is not the window's {W}x{H}"
        ptr = ri.GetImage()  # a SWIG-style pointer string: _<hex address>_p_void
        addr = int(ptr[1:].split("_", 1)[0], 16)
        raw = np.frombuffer((ctypes.c_uint16 * (mw * mh * 4)).from_address(addr), np.uint16).reshape(mh, mw, 4)
        out = np.zeros((H, W, 4))
        uw, uh = min(uw, W - ox), min(uh, H - oy)
        out[oy:oy + uh, ox:ox + uw] = raw[:uh, :uw] / FP_SCALE
        return out[::-1].copy()


class GpuRayCast(_VtkPeer):
    """vtkOpenGLGPUVolumeRayCastMapper (on the OpenGL the window gets: `renderer_name`); the window's RGBA."""

    name = "VTK GPU"

    def _mapper(self, threads: int) -> Any:
        m = self.vtk.vtkOpenGLGPUVolumeRayCastMapper()
        m.SetUseJittering(0)
        return m

    def _image(self, W: int, H: int) -> np.ndarray:
        from vtk.util import numpy_support

        arr = self.vtk.vtkFloatArray()
        self.window.GetRGBAPixelData(0, 0, W - 1, H - 1, 0, arr)
        return numpy_support.vtk_to_numpy(arr).reshape(H, W, 4)[::-1].astype(np.float64)
