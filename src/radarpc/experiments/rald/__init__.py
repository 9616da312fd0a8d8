"""RaLD: dense 3-D point clouds from one radar frame by radar-conditioned latent diffusion."""
