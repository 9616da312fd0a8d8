"""Training: one loop for every model (:mod:`radarpc.training.loop`), safetensors checkpoints."""
