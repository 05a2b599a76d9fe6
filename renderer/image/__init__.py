"""The image out: the render result and its encodings (PNG, .npy), and CIE76 ΔE in CIELUV between images."""
