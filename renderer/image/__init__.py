"""The image out: the render result, its report (typed, each key documented), its encodings (PNG, .npy), and CIE76
ΔE in CIELUV between images."""
