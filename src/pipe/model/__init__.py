"""The model's core: interfaces of the three plugin kinds, the shared VAE machinery, losses and the solver."""
