"""What each key of a render's report means (`RenderResult.report`, the HTTP `X-Lodcast-Report` header, jobs'
reports, `lodcast render --report`). docs/reference.md is generated from this table, and a test checks that a
render's report has exactly these keys."""
from __future__ import annotations

__all__ = ["REPORT_FIELDS"]

REPORT_FIELDS: dict[str, str] = {
    "wall_ms": "the whole render, milliseconds: selection, brick reads, uploads, kernel, read-back",
    "kernel_ms": "the ray-casting kernel alone (OpenCL profiling), milliseconds",
    "bricks_read": "bricks read from the store for this render (the rest were on the device or in the brick cache)",
    "bricks_cached": "bricks not read: the device had them (the same selection, or the same block at the same level in the last atlas of this store) or the brick cache did",
    "bricks_skipped": "blocks the selection left out: invisible under the transfer function",
    "reduction": "data reduction of the level-of-detail selection: level-0 bytes of the visible blocks / bytes used",
    "predicted_delta_e": "the predicted mean image error, ΔE (CIE76 in CIELUV), against the reference (full "
                         "resolution at step ¼): the level of detail's own (its selection's) plus the step's (a "
                         "calibrated model of the unshaded composite; 0 for an array and in the projection modes)",
    "samples": "samples the rays took",
    "estimated_samples": "samples estimated before the render started (the cost LODCAST_MAX_SAMPLES limits)",
    "launches": "kernel launches (bands of rows, so that a long render can stop between them)",
    "build_options": "the -D flags the kernel was compiled with: what the scene uses, nothing else",
    "program_cache": "where the compiled kernel came from: memory, disk or a fresh build",
    "build_ms": "kernel build (or cache lookup), milliseconds",
    "upload_ms": "volume data uploaded to the device, milliseconds",
    "quality": "the quality asked for: full, lossless, {reduction} or {budget_mb}",
    "level": "the store level rendered when one level was asked for, else null",
    "interpolation": "sampling across blocks of different levels: interblock or nearest_block",
    "classification": "how coarse samples were classified: by their distribution, by the mean, or point (level 0)",
    "coarse_cells": "cells of coarse blocks whose level-0 voxels the TF shows nothing of: skipped (what the coarse "
                    "field shows there is blur or a distribution's tail), or sampled on a store of format < 3, "
                    "which keeps no level-0 cell ranges; null without coarse blocks or outside composite mode",
    "adaptive": "adaptive object-space sampling: false, or how it was limited",
    "lod_visibility": "whether the level-of-detail selection weighed what the camera sees of each block "
                      "(sampling.lod_visibility, at the budgeted qualities)",
    "blocks": "blocks of the volume",
    "step_world": "the sampling step in world units",
    "unit_distance": "the length (world units) a TF's opacity is given for",
    "lut_entries": "entries of the classification table",
    "lut_exact": "whether the table holds the TF exactly (every control point on an entry)",
    "preintegration_ms": "building the pre-integration table, milliseconds (null without pre-integration)",
    "tf2": "whether a second transfer function was composited",
    "priority_map": "the dual-TF priority map's statistics, or null",
    "adaptive_screen": "adaptive screen-space sampling's statistics, or null",
    "device_bytes": "volume data on the device at once, bytes (within LODCAST_DEVICE_BUDGET_MB)",
    "passes": "passes the render took: more than 1 when the data exceeded the device budget",
    "width": "image width, pixels",
    "height": "image height, pixels",
    "device": "the OpenCL device",
}
