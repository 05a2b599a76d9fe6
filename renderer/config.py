"""KernelConfig: everything that specialises the kernel, frozen, turned into `-D` options — the only way a
scene changes the compiled code (no source pasting). Features a scene does not use are compiled out."""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["KernelConfig", "PRECISE_SAMPLES"]

#: Rays with more samples than this use compensated sums (the error of plain float32 sums grows with the count).
PRECISE_SAMPLES = 4096


@dataclass(frozen=True)
class KernelConfig:
    sampler: str = "full"  # "full": level 0 from a plain buffer; "atlas": the LOD brick atlas (lc_atlas.h)
    interpolation: str = "trilinear"  # atlas only: "nearest_block" | "interblock"
    adaptive: bool = False  # atlas only: adaptive object-space sampling, limited at block boundaries
    adaptive_naive: bool = False  # with adaptive: the naive variant (benchmarks only)
    distribution: bool = False  # atlas, composite: classify coarse samples by their distribution (LC_DIST)
    mode: str = "composite"  # "composite" | "mip"
    orthographic: bool = False
    ess: bool = True
    jitter: bool = False
    precise: bool = False
    background: bool = False
    clip: bool = False  # clip planes (a crop box alone needs no option: the host shrinks the box)
    shade: bool = False  # local illumination (composite only)
    preint: bool = False  # pre-integrated classification (composite only)

    def __post_init__(self) -> None:
        if self.sampler not in ("full", "atlas"):
            raise ValueError(f"sampler {self.sampler!r} is not implemented")
        if self.sampler == "atlas" and self.interpolation not in ("nearest_block", "interblock"):
            raise ValueError(f"interpolation {self.interpolation!r} is not implemented for the atlas")
        if (self.adaptive or self.adaptive_naive) and self.sampler != "atlas":
            raise ValueError("adaptive object-space sampling needs the atlas sampler (a level-of-detail quality)")
        if self.mode not in ("composite", "mip"):
            raise ValueError(f"mode {self.mode!r} is not implemented")
        if self.distribution and (self.sampler != "atlas" or self.mode != "composite"):
            raise ValueError("distribution classification needs the atlas sampler and composite mode")
        if (self.shade or self.preint) and self.mode != "composite":
            raise ValueError("shading and pre-integration need composite mode")

    def build_options(self) -> tuple[str, ...]:
        opts = [f"-DLC_SAMPLER_{self.sampler.upper()}"]
        if self.sampler == "atlas":
            opts.append("-DLC_INTERP_II" if self.interpolation == "interblock" else "-DLC_INTERP_NB")
            if self.adaptive or self.adaptive_naive:
                opts.append("-DLC_ADAPTIVE")
            if self.adaptive_naive:
                opts.append("-DLC_ADAPTIVE_NAIVE")
            if self.distribution:
                opts.append("-DLC_DIST")
        if self.mode == "mip":
            opts.append("-DLC_MODE_MIP")
        for flag, name in (
            (self.orthographic, "LC_ORTHO"),
            (self.ess, "LC_ESS"),
            (self.jitter, "LC_JITTER"),
            (self.precise and self.mode == "composite", "LC_PRECISE"),
            (self.background, "LC_BACKGROUND"),
            (self.clip, "LC_CLIP"),
            (self.shade, "LC_SHADE"),
            (self.preint, "LC_PREINT"),
        ):
            if flag:
                opts.append(f"-D{name}")
        return tuple(opts)
