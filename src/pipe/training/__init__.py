"""Training with Lightning: stage 1 the point-cloud VAE, stage 2 the head through the dynamic model."""
