"""How much does a stage-2 run's radar lower its EDM loss, noise level by noise level? For the radar
check's 72 validation frames (radarpc.experiments.rald.task.radar_swap_pairs: each beside the frame
half the split away, another run's), the loss of the frames' latents (posterior means) at fixed
sigmas, the same noise, with the frame's own radar and with the other frame's; then the condition
tokens' spread across frames against their spread across tokens.
Run from the folder holding runs/ and data/:  python this.py RUN [RUN ...]"""
import sys

import numpy as np
import torch

from radarpc.experiments.rald.runs import load_rald
from radarpc.experiments.rald.task import DiffusionFrames, radar_swap_pairs
from radarpc.models.edm import edm_loss_weight

torch.set_num_threads(2)
SIGMAS = (0.05, 0.2, 0.5, 1.0, 2.0, 5.0, 20.0)
for path in sys.argv[1:]:
    run = load_rald(path)
    cfg = run.config
    ds = DiffusionFrames(run.key["data"], "val", run.ae_config.data, cfg.model.config.radar_shape,
                         cfg.radar.max_intensity_db, training=False, scenes=cfg.scenes)
    pairs = radar_swap_pairs(len(ds))
    own_sum, other_sum = np.zeros(len(SIGMAS)), np.zeros(len(SIGMAS))
    tokens = []
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for k in range(0, len(pairs), 8):
            chunk = pairs[k:k + 8]
            points = torch.stack([ds[i][1] for i, _ in chunk])
            z = run.ae.encode(points)[0].float()                                   # (B, M, D) posterior means
            c_own = run.dit.encode_radar(torch.stack([ds.radar(i) for i, _ in chunk]))
            c_other = run.dit.encode_radar(torch.stack([ds.radar(j) for _, j in chunk]))
            tokens.append(c_own)
            noise = torch.randn(z.shape, generator=g)
            for s, sigma in enumerate(SIGMAS):
                sig = torch.full((z.shape[0],), sigma)
                x = z + noise * sigma
                w = float(edm_loss_weight(torch.tensor(sigma)))
                own_sum[s] += float((w * (run.dit(x, sig, c_own) - z) ** 2).mean((1, 2)).sum())
                other_sum[s] += float((w * (run.dit(x, sig, c_other) - z) ** 2).mean((1, 2)).sum())
    n = len(pairs)
    t = torch.cat(tokens)                                                          # (F, T, W)
    across_frames = float(t.var(0).mean())                                         # per token and channel, over frames
    across_tokens = float(t.mean(0).var(0).mean())                                 # of the frame-mean tokens
    print(f"{path}: {n} frames, best weights of step {run.status['weights_step']}")
    print("sigma      " + " ".join(f"{s:>7g}" for s in SIGMAS))
    print("own radar  " + " ".join(f"{v / n:7.4f}" for v in own_sum))
    print("other      " + " ".join(f"{v / n:7.4f}" for v in other_sum))
    print("gain       " + " ".join(f"{(o - w) / n:7.4f}" for w, o in zip(own_sum, other_sum)))
    print(f"condition tokens: variance across frames {across_frames:.4g}, across token positions {across_tokens:.4g}")
