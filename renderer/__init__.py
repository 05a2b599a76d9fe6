"""lodcast.renderer: the OpenCL ray caster and everything a render needs on the host, in the order a frame flows.

  engine.py, cache.py   the engine's state (device, caches, settings) and the byte-bounded LRU its caches are
  scene/                what a request asks for: scene model, transfer functions, presets, camera, clip, cost
  lod/                  level of detail: significance, per-level error, selection, visibility, classification
  data/                 volume data to the device: volume view, bricks, level 0 and the atlas, cells, passes
  walk/                 which cells a ray may skip and how far it may leap
  kernel/               the OpenCL sources and what the host hands them: config, parameters, tables
  frame/                one frame: plan, preparation, launch and report (Renderer), screen-space tiles
  image/                the result and its typed report, its encodings, and ΔE between images
  tools/                `lodcast render`, `lodcast demo`'s pictures, `lodcast report`

The public verbs (`lodcast.Renderer`, `lodcast.render`, `RenderResult`, `Scene`) are re-exported lazily by
`lodcast`. Importing this package imports nothing heavy: pyopencl loads with the modules that launch kernels.
"""
