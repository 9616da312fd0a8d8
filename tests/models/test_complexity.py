"""Convolution MACs counted on a hand-worked network."""
import pytest
import torch

from radarpc.models.complexity import conv_gmac


class _Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(4, 6, 3, padding=1, groups=2)          # 4 x 6 outputs of 6 channels
        self.up = torch.nn.ConvTranspose2d(6, 5, 3, stride=(2, 1), padding=1, output_padding=(1, 0))
        self.act = torch.nn.ReLU()
        self.head = torch.nn.Conv2d(5, 1, 1)

    def forward_channels(self, x):
        return self.up(self.act(self.conv(x)))

    def forward(self, x):
        return self.head(self.forward_channels(x))


def test_conv_gmac_counts_convolutions_and_transposed_convolutions():
    net, x = _Net(), torch.randn(1, 4, 4, 6)
    # conv: 6 x 4 x 6 outputs, each 3 x 3 x (4 / 2) MACs = 144 x 18; transposed: each of its
    # 6 x 4 x 6 inputs feeds 3 x 3 x 5 outputs = 144 x 45
    body = (144 * 18 + 144 * 45) / 1e9
    assert conv_gmac(net, x, forward=net.forward_channels) == pytest.approx(body, rel=1e-12)
    # the whole forward adds the 1 x 1 head: its 8 x 6 outputs take 5 MACs each
    assert conv_gmac(net, x) == pytest.approx(body + 8 * 6 * 5 / 1e9, rel=1e-12)
    # a batch of two costs twice as much, and the hooks are gone afterwards
    assert conv_gmac(net, torch.randn(2, 4, 4, 6)) == pytest.approx(2 * (body + 240 / 1e9), rel=1e-12)
    assert not any(m._forward_hooks for m in net.modules())


class _Clock:
    """A fake ``time.perf_counter`` / ``process_time``: it moves only when a frame runs."""

    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_frames_per_second_is_the_median_of_timed_sweeps_after_warm_up(monkeypatch):
    from radarpc.models import complexity

    clock = _Clock()
    monkeypatch.setattr(complexity.time, "perf_counter", clock)
    calls = []
    cost = {"a": 0.1, "b": 0.2, "c": 0.3}          # seconds a frame, 0.6 a sweep

    def run(frame):
        calls.append(frame)
        timed = len(calls) - 2                      # after the 2 warm-up calls
        slower = 1.0 if timed <= 0 else 1.0 + 0.5 * ((timed - 1) // 3)   # sweeps 0, 1, 2: x1, x1.5, x2
        clock.t += cost[frame] * slower

    rate = complexity.frames_per_second(run, ["a", "b", "c"], "cpu", repeats=3, warmup=2)
    assert calls == ["a", "a"] + ["a", "b", "c"] * 3
    # sweeps of 0.6, 0.9 and 1.2 s over 3 frames: 5, 3.33 and 2.5 frames/s
    assert rate.sweeps == pytest.approx((5.0, 10 / 3, 2.5), rel=1e-12)
    assert (rate.median, rate.low, rate.high, rate.repeats) == pytest.approx((10 / 3, 2.5, 5.0, 3), rel=1e-12)
    assert rate.text() == "3.33 frames/s (2.5-5 over 3 sweeps)"
    empty = complexity.frames_per_second(run, [], "cpu")
    assert empty.repeats == 0 and empty.text() == "n/a frames/s (no frames)"
    with pytest.raises(ValueError, match="repeats must be an integer >= 1"):
        complexity.frames_per_second(run, ["a"], repeats=0)


def test_time_interleaved_runs_methods_pass_by_pass(monkeypatch):
    from radarpc.models import complexity

    wall, cpu = _Clock(), _Clock()
    monkeypatch.setattr(complexity.time, "perf_counter", wall)
    monkeypatch.setattr(complexity.time, "process_time", cpu)
    order = []

    def method(name, seconds):
        def run(i):
            order.append((name, i))
            wall.t += seconds
            cpu.t += 2 * seconds                   # two threads busy
        return run

    times = complexity.time_interleaved({"x": method("x", 0.5), "y": method("y", 0.25)}, 2, 2, warmup=1)
    assert order == [("x", 0), ("x", 1), ("y", 0), ("y", 1)] * 3     # one warm-up pass, two timed
    assert times["x"].wall_s == pytest.approx((0.5, 0.5)) and times["x"].cpu_s == pytest.approx((1.0, 1.0))
    assert times["y"].first_s == pytest.approx(0.25) and times["y"].wall_s == pytest.approx((0.25, 0.25))
    assert complexity.time_interleaved({"x": method("x", 1.0)}, 1, 1, warmup=0)["x"].first_s is None


def test_peak_memory_sees_a_tensor_allocated_inside_the_block():
    from radarpc.models.complexity import MEMORY_METHODS, PeakMemory

    n = 64 * 2 ** 20                                   # bytes: 16 Mi float32
    with PeakMemory("cpu") as probe:
        x = torch.ones(n // 4)                         # written, so resident
        del x
    mem = probe.memory
    assert mem.method in MEMORY_METHODS
    if mem.method == "rss-peak-reset":
        # Linux: the peak is reset at the start, so the tensor's pages count whole; the resident set
        # also holds file-backed pages (shared libraries) the kernel may drop meanwhile, hence the
        # few MiB of slack below, and the allocator's own pages above
        assert n - 4 * 2 ** 20 <= mem.working_bytes < n + 32 * 2 ** 20
        assert mem.peak_bytes == mem.baseline_bytes + mem.working_bytes
    with PeakMemory("cpu") as idle:
        pass
    if idle.memory.method == "rss-peak-reset":
        assert idle.memory.working_bytes < 8 * 2 ** 20
