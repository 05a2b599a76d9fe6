"""lodcast.renderer: the OpenCL ray caster and everything a render needs on the host.

Public API (re-exported lazily by `lodcast`):
  render(store, scene) -> RenderResult     render.py   (.rgba float32 premultiplied H×W×4, .report dict)
  Scene, SceneError, TransferFunction      scene.py    (one pydantic model for CLI, HTTP, jobs and client)
  save_image / png_bytes                   image.py    (PNG straight alpha 8-bit, .npy float32 premultiplied)
  render_demo(store, out_dir)              demo.py     (pictures for `lodcast demo`)

Inside: camera.py (DESIGN.md's camera), transfer_function.py (exact opacity correction, the kernel LUT, block
visibility for empty-space skipping), volume.py (the only module that touches the store), sampler.py (level 0 on
the device), atlas.py (LOD: brick cache, atlas and block index map, adaptive step levels; sampled by lc_atlas.h
with nearest-block or interblock interpolation), config.py (KernelConfig -> -D options), lodcast/opencl.py (device, build and cache: below the store and the renderer), structs.py (NumPy mirror of
lc_types.h), raycast.cl / march_bare.cl / probe.cl / atlas_probe.cl with lc_types.h and lc_common.h, cli_render.py (`lodcast
render`). Importing this package imports nothing heavy: pyopencl loads with render.py / lodcast.opencl only.
"""
