"""The walks (Open VKL's interval iterator, where data/ is the sampler): which cells a ray may skip and how far it may leap."""
