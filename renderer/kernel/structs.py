"""NumPy mirrors of the structs in lc_types.h (checked field by field by tests/test_renderer_structs.py)."""
from __future__ import annotations

import numpy as np

__all__ = ["PARAMS_DTYPE", "STATE_FLOATS", "new_params"]

_V4F = (np.float32, (4,))
_V4I = (np.int32, (4,))

#: LcParams. Order, types and offsets must match lc_types.h exactly; append only.
PARAMS_DTYPE = np.dtype(
    [
        ("eye", _V4F),
        ("cam_f", _V4F),
        ("cam_r", _V4F),
        ("cam_u", _V4F),
        ("box_lo", _V4F),
        ("box_hi", _V4F),
        ("origin", _V4F),
        ("inv_spacing", _V4F),
        ("background", _V4F),
        ("dims", _V4I),
        ("grid", _V4I),
        ("half_w", np.float32),
        ("half_h", np.float32),
        ("step", np.float32),
        ("inv_unit", np.float32),
        ("lut_lo", np.float32),
        ("lut_scale", np.float32),
        ("lut_n", np.int32),
        ("early_term", np.float32),
        ("width", np.int32),
        ("height", np.int32),
        ("seed", np.uint32),
        ("max_samples", np.int32),
        ("lut_vis_lo", np.float32),
        ("lut_vis_hi", np.float32),
        ("dist_n", np.int32),
        ("dist_rows", np.int32),
        ("dist_lo", np.float32),
        ("dist_scale", np.float32),
        ("dist_sscale", np.float32),
        ("jitter", np.int32),
        ("clip", (np.float32, (6, 4))),
        ("light", _V4F),
        ("shade", _V4F),
        ("shade_gmin", np.float32),
        ("n_clip", np.int32),
        ("pre_n", np.int32),
        ("pre_knots", np.int32),
        ("ortho", np.int32),
        ("iso", np.float32),
        ("shade_gref", np.float32),
        ("grad_op", np.float32),
        ("tf2_lut_at", np.int32),
        ("tf2_ext_at", np.int32),
        ("tf2_dtab_at", np.int32),
        ("tf2_ptab_at", np.int32),
        ("tf2_lut_lo", np.float32),
        ("tf2_lut_scale", np.float32),
        ("tf2_lut_n", np.int32),
        ("tf2_vis_lo", np.float32),
        ("tf2_vis_hi", np.float32),
        ("tf2_inv_unit", np.float32),
        ("tf2_dist_n", np.int32),
        ("tf2_dist_lo", np.float32),
        ("tf2_dist_scale", np.float32),
        ("tf2_pre_knots", np.int32),
        ("tf2_grad_op", np.float32),
        ("tf2_pre_n", np.int32),
        ("prio_tile", np.int32),
        ("prio_w", np.int32),
        ("screen_n", np.int32),
        ("pad5", np.int32),
        ("pass_lo", _V4F),
        ("pass_hi", _V4F),
        ("pass_off", _V4I),
        ("pass_dims", _V4I),
        ("pass_first", np.int32),
        ("leap_planes", np.uint32),
        ("pad7", np.int32),
        ("pad8", np.int32),
        ("ess_grid", _V4I),
    ],
    align=True,
)
assert PARAMS_DTYPE.itemsize == 592 and PARAMS_DTYPE.itemsize % 16 == 0


#: LC_PASSES: floats of ray state kept per ray between passes (lc_integrator.h's LC_STATE_FLOATS)
STATE_FLOATS = 32


def new_params() -> np.ndarray:
    """A zeroed LcParams record (shape (1,), ready to upload)."""
    return np.zeros(1, dtype=PARAMS_DTYPE)
