"""What a request asks for: the scene model, transfer functions and presets (fixed and adaptive), the camera, clipping and the cost estimate."""
