"""KernelConfig: everything that specialises the kernel, frozen, turned into `-D` options — the only way a
scene changes the compiled code (no source pasting). Features a scene does not use are compiled out; what costs
a ray nothing measurable as a branch on its parameters (the projection, jitter, the background) is not an option,
so that scenes differing only there share one program."""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["KernelConfig", "PRECISE_SAMPLES", "MODES", "EXTREMUM_MODES", "VOXEL_TYPES", "voxel_define"]

MODES = ("composite", "mip", "minip", "average", "iso")
#: projections by an extremum: the block walk skips blocks that cannot beat the extremum so far
EXTREMUM_MODES = ("mip", "minip")

#: OpenCL C types of the voxels a kernel reads (renderer/kernel/lc_common.h's LC_VOXEL; float unless told otherwise)
VOXEL_TYPES = ("float", "char", "uchar", "short", "ushort")


def voxel_define(ctype: str) -> tuple[str, ...]:
    """The -D option that makes a kernel read voxels of OpenCL C type `ctype` (none for float)."""
    return () if ctype == "float" else (f"-DLC_VOXEL={ctype}",)


#: Rays with more samples than this use compensated sums (the error of plain float32 sums grows with the count).
PRECISE_SAMPLES = 4096


@dataclass(frozen=True)
class KernelConfig:
    sampler: str = "full"  # "full": level 0 from a plain buffer; "atlas": the LOD brick atlas (lc_atlas.h)
    interpolation: str = "trilinear"  # atlas only: "nearest_block" | "interblock"
    adaptive: bool = False  # atlas only: adaptive object-space sampling, limited at block boundaries
    adaptive_naive: bool = False  # with adaptive: the naive variant (benchmarks only)
    lattice: bool = False  # with adaptive: level 0 after a coarse cell on full resolution's lattice too ("lossless")
    distribution: bool = False  # atlas, composite: classify coarse samples by their distribution (LC_DIST)
    mode: str = "composite"  # "composite" | "mip" | "minip" | "average" | "iso"
    ess: bool = True
    octant_cells: bool = True  # the blocks' half-block cells have octants worth walking (render.kernel_config)
    precise: bool = False
    clip: bool = False  # clip planes (a crop box alone needs no option: the host shrinks the box)
    shade: bool = False  # local illumination (composite only)
    preint: bool = False  # pre-integrated classification (composite only)
    gradient_opacity: bool = False  # a TF's extinction scaled by the gradient magnitude (composite only)
    tf2: bool = False  # dual-TF compositing, a second TF integrated concurrently (composite only)
    screen: bool = False  # adaptive screen-space sampling: rays through given image positions (tile samples)
    passes: bool = False  # one pass of a render in several (the volume data exceeds the device budget)
    voxel: str = "float"  # the OpenCL C type of the volume's and atlas's voxels (VOXEL_TYPES)

    def __post_init__(self) -> None:
        if self.sampler not in ("full", "atlas"):
            raise ValueError(f"sampler {self.sampler!r} is not implemented")
        if self.sampler == "atlas" and self.interpolation not in ("nearest_block", "interblock"):
            raise ValueError(f"interpolation {self.interpolation!r} is not implemented for the atlas")
        if (self.adaptive or self.adaptive_naive) and self.sampler != "atlas":
            raise ValueError("adaptive object-space sampling needs the atlas sampler (a level-of-detail quality)")
        if self.mode not in MODES:
            raise ValueError(f"mode {self.mode!r} is not implemented")
        if self.distribution and (self.sampler != "atlas" or self.mode != "composite"):
            raise ValueError("distribution classification needs the atlas sampler and composite mode")
        if self.shade and self.mode not in ("composite", "iso"):
            raise ValueError("shading needs composite or iso mode")
        if self.preint and self.mode != "composite":
            raise ValueError("pre-integration needs composite mode")
        if self.gradient_opacity and self.mode != "composite":
            raise ValueError("gradient opacity needs composite mode")
        if self.tf2 and self.mode != "composite":
            raise ValueError("a second transfer function (tf2) needs composite mode")
        if self.lattice and not self.adaptive:
            raise ValueError("the lattice option belongs to adaptive object-space sampling")
        if self.passes and self.adaptive_naive:
            raise ValueError("naive adaptive sampling cannot be split into passes (its steps run across blocks)")
        if self.voxel not in VOXEL_TYPES:
            raise ValueError(f"voxel type {self.voxel!r} is not implemented")
        if self.ess and self.mode in ("average", "iso"):
            raise ValueError(f"mode {self.mode!r} reads every sample: no empty-space skipping")

    @property
    def leap(self) -> bool:
        """Space leaping over empty cells (LC_LEAP): the kernel reads the walk's octant distances (renderer/walk/leap.py).
        Where the walk's skip depends on the ray (MIP, a second TF) or on a pass's blocks it walks cell by cell."""
        return self.ess and self.mode == "composite" and not self.tf2 and not self.passes and not self.adaptive_naive

    @property
    def octants(self) -> bool:
        """The adaptive walk's octant masks (LC_OCTANTS): a sampled half-block cell's walk info holds which of its
        eight octants (quarter-block cells) can show something, and samples in the others are not taken. With
        pre-integration every sample is a segment's end and stays."""
        return self.leap and self.adaptive and self.sampler == "atlas" and not self.preint and self.octant_cells

    def build_options(self) -> tuple[str, ...]:
        opts = [f"-DLC_SAMPLER_{self.sampler.upper()}"]
        if self.sampler == "atlas":
            opts.append("-DLC_INTERP_II" if self.interpolation == "interblock" else "-DLC_INTERP_NB")
            if self.adaptive or self.adaptive_naive:
                opts.append("-DLC_ADAPTIVE")
            if self.adaptive_naive:
                opts.append("-DLC_ADAPTIVE_NAIVE")
            if self.lattice:
                opts.append("-DLC_LATTICE")
            if self.distribution:
                opts.append("-DLC_DIST")
        opts += {"mip": ["-DLC_MODE_MIP"], "minip": ["-DLC_MODE_MIP", "-DLC_MINIP"], "average": ["-DLC_MODE_AVG"],
                 "iso": ["-DLC_MODE_ISO"]}.get(self.mode, [])
        for flag, name in (
            (self.ess, "LC_ESS"),
            (self.leap, "LC_LEAP"),
            (self.octants, "LC_OCTANTS"),
            (self.precise and self.mode == "composite", "LC_PRECISE"),
            (self.clip, "LC_CLIP"),
            (self.shade, "LC_SHADE"),
            (self.preint, "LC_PREINT"),
            (self.gradient_opacity, "LC_GRADIENT_OPACITY"),
            (self.tf2, "LC_TF2"),
            (self.screen, "LC_SCREEN"),
            (self.passes, "LC_PASSES"),
        ):
            if flag:
                opts.append(f"-D{name}")
        return tuple(opts) + voxel_define(self.voxel)
