"""RADIal's box positions (:func:`radarpc.models.targets.ra_to_box_xy`) are the same on every call
of every process, the first included.

On torch 2.13's CPU wheel the first MKL VML call (``sin``, ``cos``, ``sqrt``, ...) that an OpenMP
worker ran after MKL or oneDNN work came out of some fresh processes at reduced accuracy (20 of 40
processes in docs/results/vml_first_call.md; ``docs/notebook/scripts/vml_first_call.py``), which
moved NMS and true-positive decisions of the same weights from run to run. Each trial here is a
fresh process that runs what a pillar model's forward starts with (a Linear + GELU on 156 points,
scattered into a 4 x 8 x 128 x 224 canvas, one 3 x 3 convolution) and then computes the boxes of
114,688 detections (over torch's 32,768-element grain, so torch would split the work between
threads) twice: the two must agree exactly.
"""
import json
import subprocess
import sys

TRIAL = """
import json
import torch
import torch.nn.functional as F
from radarpc.boxes import ra_to_box_xy

g = torch.Generator().manual_seed(0)
x = torch.rand(114_688, generator=g) + 0.1
n, c, (h, w) = 156, 8, (128, 224)
with torch.inference_mode():
    feat = F.gelu(F.linear(torch.randn(n, 12, generator=g), torch.randn(c, 12, generator=g)))
    canvas = feat.new_zeros(4 * h * w, c).index_copy_(0, torch.randperm(4 * h * w, generator=g)[:n], feat)
    F.conv2d(canvas.view(4, h, w, c).permute(0, 3, 1, 2), torch.randn(c, c, 3, 3, generator=g), padding=1)
r, az = x * 100, (x - 0.6) * 150
y1, y2 = ra_to_box_xy(r, az), ra_to_box_xy(r, az)
print(json.dumps({"max_abs_diff": (y1 - y2).abs().max().item(), "shape": list(y1.shape)}))
"""


def test_box_positions_agree_from_the_first_call_in_fresh_processes():
    for _ in range(2):
        res = subprocess.run([sys.executable, "-c", TRIAL], capture_output=True, text=True, check=True)
        out = json.loads(res.stdout)
        assert out == {"max_abs_diff": 0.0, "shape": [114_688, 2]}
