"""A render's report, typed: `RenderReport` (a TypedDict: at run time the report stays a plain, JSON-ready dict) and
`REPORT_FIELDS`, what each of its keys means. The report is `RenderResult.report`, the HTTP `X-Lodcast-Report`
header, jobs' reports and `lodcast render --report`. docs/reference.md is generated from both (the key, its type
and its meaning), and a test checks that a render's report has exactly these keys, each value of its type.

Over HTTP the report has been through JSON: a float that is not finite (a `reduction` of infinity, when nothing is
loaded) arrives as null."""
from __future__ import annotations

from typing import Any, Literal, TypedDict

__all__ = ["RenderReport", "PriorityMapReport", "ScreenReport", "ChosenSetting", "ChosenReport", "REPORT_FIELDS"]


class PriorityMapReport(TypedDict):
    """The dual-TF priority map of a render: its tile size, the share of pixels with priority (their rays integrate
    tf2), and the samples taken by the pixels with and without it."""

    tile: int
    priority_pixels: float
    samples_priority: int
    samples_other: int


class ScreenReport(TypedDict):
    """Adaptive screen-space sampling in a render: the statistic, the tile size, the rays cast (against one per
    pixel), the tiles per resolution ("4x4": count) and the reconstruction's time."""

    statistic: str
    tile: int
    rays: int
    rays_per_pixel: float
    tiles: dict[str, int]
    reconstruct_ms: float


class ChosenSetting(TypedDict):
    """A setting a quality target weighed (renderer/frame/target.py): quality (full, lossless or a reduction), step,
    interpolation (null at full), adaptive screen-space sampling, the data reduction, and its predicted ΔE and
    milliseconds (by the engine's cost model of its device)."""

    quality: str | dict[str, float]
    step: float
    interpolation: str | None
    adaptive_screen: bool
    reduction: float
    predicted_delta_e: float
    predicted_ms: float


class ChosenReport(TypedDict):
    """What a quality target picked: the target, the setting and the runner-up's (null when there was none), why,
    how many candidates there were and how many on their Pareto front, and what choosing took (milliseconds)."""

    target: dict[str, float]
    setting: ChosenSetting
    runner_up: ChosenSetting | None
    why: str
    candidates: int
    front: int
    choose_ms: float


class RenderReport(TypedDict):
    """What a render did, key by key (each key's type and meaning: docs/reference.md, made from this class and
    `REPORT_FIELDS`); at run time a plain, JSON-ready dict."""

    wall_ms: float
    kernel_ms: float
    bricks_read: int
    bricks_cached: int
    bricks_skipped: int
    reduction: float | None
    predicted_delta_e: float | None
    samples: int
    estimated_samples: int
    launches: int
    build_options: list[str]
    program_cache: str
    build_ms: float
    upload_ms: float
    quality: Literal["full", "lossless"] | dict[str, Any]
    level: int | None
    interpolation: str
    classification: str
    coarse_cells: str | None
    adaptive: Literal[False, "limited", "naive"]
    lod_visibility: bool
    blocks: int
    step_world: float
    unit_distance: float
    lut_entries: int
    lut_exact: bool
    preintegration_ms: float | None
    tf2: bool
    priority_map: PriorityMapReport | None
    adaptive_screen: ScreenReport | None
    device_bytes: int
    passes: int
    width: int
    height: int
    device: str
    stage: int
    final: bool
    image_scale: float
    chosen: ChosenReport | None


#: what each key of a RenderReport means (docs/reference.md's table), in the report's order
REPORT_FIELDS: dict[str, str] = {
    "wall_ms": "the whole render, milliseconds: selection, brick reads, uploads, kernel, read-back (at a "
               "progressive render's stage: since the request, its earlier stages included)",
    "kernel_ms": "the ray-casting kernel alone (OpenCL profiling), milliseconds",
    "bricks_read": "bricks read from the store for this render (the rest were on the device or in the brick cache)",
    "bricks_cached": "bricks not read: the device had them (the same selection, or the same block at the same level in the last atlas of this store) or the brick cache did",
    "bricks_skipped": "blocks the selection left out: invisible under the transfer function",
    "reduction": "data reduction of the level-of-detail selection: level-0 bytes of the visible blocks / bytes used "
                 "(1 at quality full; infinite, null over HTTP, when nothing is loaded)",
    "predicted_delta_e": "the predicted mean image error, ΔE (CIE76 in CIELUV), against the reference (full "
                         "resolution at step ¼): the level of detail's own (its selection's) plus the step's (a "
                         "calibrated model of the unshaded composite; 0 for an array and in the projection modes; "
                         "null at a progressive render's preview of one coarse level, which has no selection)",
    "samples": "samples the rays took",
    "estimated_samples": "samples estimated before the render started (the cost LODCAST_MAX_SAMPLES limits)",
    "launches": "kernel launches (bands of rows, so that a long render can stop between them)",
    "build_options": "the -D flags the kernel was compiled with: what the scene uses, nothing else",
    "program_cache": "where the compiled kernel came from: memory, disk or a fresh build (built)",
    "build_ms": "kernel build (or cache lookup), milliseconds",
    "upload_ms": "volume data uploaded to the device, milliseconds",
    "quality": "the quality asked for: full, lossless, {reduction}, {budget_mb}, {level}, or a target, "
               "{max_delta_e} or {max_ms}; {level} also at a progressive render's preview of one coarse level",
    "level": "the store level rendered when one level was asked for ({level}, or a progressive render's preview; 0 "
             "at full), else null",
    "interpolation": "sampling across blocks of different levels: interblock or nearest_block (trilinear at "
                     "quality full)",
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
    "priority_map": "the dual-TF priority map's statistics (tile size, share of pixels with priority, samples with "
                    "and without), or null",
    "adaptive_screen": "adaptive screen-space sampling's statistics (statistic, tile size, rays and rays per pixel, "
                       "tiles per resolution, reconstruction milliseconds), or null",
    "device_bytes": "volume data on the device at once, bytes (within LODCAST_DEVICE_BUDGET_MB)",
    "passes": "passes the render took: more than 1 when the data exceeded the device budget",
    "width": "image width, pixels",
    "height": "image height, pixels",
    "device": "the OpenCL device",
    "stage": "the stage of a progressive render (0, 1, ...: coarse to fine); 0 for a plain render",
    "final": "whether this is the last stage of a progressive render, the scene's own quality (true for a plain "
             "render)",
    "image_scale": "rays per pixel edge: 1, or less at an early progressive stage rendered smaller and scaled up "
                   "to width × height",
    "chosen": "what a quality target ({max_delta_e} or {max_ms}) picked, else null: the target; the setting "
              "(quality, step, interpolation, adaptive_screen, reduction, predicted_delta_e, predicted_ms: by the "
              "engine's cost model of its device) and the runner-up's; why; how many candidates and how many on "
              "their Pareto front; choose_ms, what choosing took. The other keys describe the chosen setting's render",
}
