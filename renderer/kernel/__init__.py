"""The OpenCL kernel and what the host hands it: the .cl/.h sources, the configuration (-D options), the parameter block and its NumPy mirror, and the pre-integration tables."""
