"""EDM preconditioning, loss and Heun sampler against hand-worked values and closed forms."""
import math

import pytest
import torch

from radarpc.models.edm import (SeededNoise, edm_coefficients, edm_loss, edm_loss_weight, edm_precondition,
                                edm_sampler, edm_sigma_steps)


@pytest.mark.parametrize("sigma, sigma_data, want", [
    # sigma = sigma_data: c_skip = 1/2, c_out = c_in = 1/sqrt(2) (times sigma_data, 1/sigma_data), lambda = 2/sd^2
    (1.0, 1.0, (0.5, 1 / math.sqrt(2), 1 / math.sqrt(2), 0.0, 2.0)),
    # sigma = 2: c_skip = 1/5, c_out = 2/sqrt(5), c_in = 1/sqrt(5), c_noise = ln 2 / 4, lambda = 5/4
    (2.0, 1.0, (0.2, 2 / math.sqrt(5), 1 / math.sqrt(5), math.log(2) / 4, 1.25)),
    # sigma = 0.002: c_skip = 1/1.000004, c_out = 0.002/sqrt(1.000004), lambda = 1.000004/4e-6
    (0.002, 1.0, (1 / 1.000004, 0.002 / math.sqrt(1.000004), 1 / math.sqrt(1.000004), math.log(0.002) / 4,
                  1.000004 / 4e-6)),
    # sigma = sigma_data = 0.5: c_skip = 1/2, c_out = 0.25/sqrt(0.5), c_in = 1/sqrt(0.5), lambda = 0.5/0.0625 = 8
    (0.5, 0.5, (0.5, 0.25 / math.sqrt(0.5), 1 / math.sqrt(0.5), math.log(0.5) / 4, 8.0)),
])
def test_coefficients_and_loss_weight_by_hand(sigma, sigma_data, want):
    s = torch.tensor([sigma], dtype=torch.float64)
    got = [*edm_coefficients(s, sigma_data), edm_loss_weight(s, sigma_data)]
    for g, w in zip(got, want):
        assert g.item() == pytest.approx(w, rel=1e-14, abs=1e-15)


def test_loss_weight_is_the_inverse_square_of_c_out():
    s = torch.logspace(-3, 2, 50, dtype=torch.float64)
    _, c_out, _, _ = edm_coefficients(s, 0.7)
    torch.testing.assert_close(edm_loss_weight(s, 0.7), 1 / c_out ** 2, rtol=1e-13, atol=0)


def test_precondition_wraps_the_raw_network():
    """``D = c_skip x + c_out F(c_in x, c_noise)`` for a raw network known in closed form, with a
    per-sample sigma and with one sigma for the batch."""
    def raw(x_in, c_noise, cond):
        return 3 * x_in + c_noise[:, None, None] + cond

    x = torch.randn(2, 5, 3, dtype=torch.float64)
    sigma = torch.tensor([0.5, 4.0])
    D = edm_precondition(raw, x, sigma, 0.25, sigma_data=1.0)
    for b, s in enumerate(sigma.tolist()):
        want = 1 / (s * s + 1) * x[b] + s / math.sqrt(s * s + 1) * (3 * x[b] / math.sqrt(s * s + 1)
                                                                     + math.log(s) / 4 + 0.25)
        torch.testing.assert_close(D[b], want.to(D.dtype), rtol=1e-6, atol=1e-6)
    one = edm_precondition(raw, x, 4.0, 0.25)
    torch.testing.assert_close(one[1], D[1])


def test_loss_draws_log_normal_sigma_and_weights_the_error():
    """Against the same draws repeated by hand: ln sigma ~ N(P_mean, P_std^2) per sample, noise of
    that sigma, weight lambda(sigma)."""
    y = torch.randn(6, 4, 3)
    seen = {}

    def denoiser(x, sigma, cond):                     # a fixed, known denoiser: half the input
        seen["sigma"] = sigma
        return 0.5 * x

    loss = edm_loss(denoiser, y, None, generator=torch.Generator().manual_seed(3))
    g = torch.Generator().manual_seed(3)
    rnd = torch.randn(6, 1, 1, generator=g)
    sigma = torch.exp(rnd * 1.2 - 1.2)
    n = torch.randn(6, 4, 3, generator=g) * sigma
    want = ((sigma ** 2 + 1) / sigma ** 2 * (0.5 * (y + n) - y) ** 2).mean()
    torch.testing.assert_close(loss, want, rtol=1e-6, atol=0)
    torch.testing.assert_close(seen["sigma"], sigma.flatten())


def test_loss_sigma_distribution():
    """20,000 draws: the mean and std of ln sigma within 4 standard errors of -1.2 and 1.2."""
    got = {}

    def denoiser(x, sigma, cond):
        got["log"] = sigma.log()
        return x

    edm_loss(denoiser, torch.zeros(20000, 1), None, generator=torch.Generator().manual_seed(0))
    se = 1.2 / math.sqrt(20000)
    assert abs(got["log"].mean().item() + 1.2) < 4 * se
    assert abs(got["log"].std().item() - 1.2) < 4 * se / math.sqrt(2) * 1.5


def test_sigma_steps_closed_form():
    t = edm_sigma_steps(18, 0.002, 80.0, 7.0)
    i = torch.arange(18, dtype=torch.float64)
    want = (80 ** (1 / 7) + i / 17 * (0.002 ** (1 / 7) - 80 ** (1 / 7))) ** 7
    assert t.shape == (19,) and t.dtype == torch.float32 and t[-1] == 0
    # float32: a few ulp (2^-24 each) on the base, times rho = 7 through the power
    torch.testing.assert_close(t[:-1].double(), want, rtol=7 * 4 * 2 ** -24, atol=0)
    assert t[0].item() == pytest.approx(80, rel=1e-6) and t[17].item() == pytest.approx(0.002, rel=1e-6)
    assert bool((t[1:] < t[:-1]).all())


@pytest.mark.parametrize("bad", [dict(num_steps=1), dict(sigma_min=0.0), dict(sigma_min=90.0), dict(rho=0.0)])
def test_sigma_steps_refuse_bad_settings(bad):
    with pytest.raises(ValueError, match="edm sampler"):
        edm_sigma_steps(**{**dict(num_steps=18, sigma_min=0.002, sigma_max=80.0, rho=7.0), **bad})


@pytest.mark.parametrize("num_steps", [18, 5])
def test_sampler_calls_the_denoiser_2n_minus_1_times_with_one_condition(num_steps):
    calls = []
    condition = object()

    def denoiser(x, sigma, cond):
        calls.append((sigma.clone(), cond))
        assert sigma.shape == (x.shape[0],)
        return torch.zeros_like(x)

    edm_sampler(denoiser, torch.randn(3, 4, 2), condition, num_steps=num_steps)
    assert len(calls) == 2 * num_steps - 1               # 35 for 18 steps
    assert all(c is condition for _, c in calls)
    t = edm_sigma_steps(num_steps)
    # Euler at t_0 .. t_{N-1}, each but the last followed by the correction at t_{i+1}
    want = [t[0]] + [s for i in range(1, num_steps) for s in (t[i], t[i])]
    assert [s[0].item() for s, _ in calls] == [w.item() for w in want]


def test_sampler_with_the_exact_denoiser_lands_on_the_modes():
    """Data +-1 per element, equally likely: the exact denoiser is ``E[y | x] = tanh(x / sigma^2)``.
    The last step (t_17 = 0.002 -> 0) is Euler, which returns ``D(x; 0.002) = tanh(x / 4e-6)``: that
    is +-1 to float32 rounding for every ``|x| > 3.6e-5`` (tanh(9) rounds to 1), so every element
    lands within 1 ulp of a mode; by symmetry half of them on each."""
    noise = torch.randn(4096, 1, generator=torch.Generator().manual_seed(0))
    x = edm_sampler(lambda x, s, c: torch.tanh(x / s[:, None] ** 2), noise, None)
    assert (x.abs() - 1).abs().max().item() <= 2 ** -23
    assert abs((x > 0).float().mean().item() - 0.5) < 4 * 0.5 / math.sqrt(4096)


def test_sampler_with_the_exact_gaussian_denoiser_is_heuns_recursion():
    """Gaussian data N(0, s^2): ``D = x s^2 / (s^2 + sigma^2)``, so the ODE is linear,
    ``dx/dsigma = a(sigma) x`` with ``a = sigma / (s^2 + sigma^2)``, and each Heun step multiplies x
    by ``1 + h (a(t) + a(t') (1 + h a(t))) / 2`` (``h = t' - t``; the last, Euler, by
    ``1 + h a(t)``): the sampler's result against that product, in float64. The ODE's own solution,
    ``x(0) = x(80) s / sqrt(s^2 + 80^2)``, is met to 6 % by these 18 coarse steps."""
    s2 = 0.49
    noise = torch.randn(64, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    x = edm_sampler(lambda x, sig, c: x * s2 / (s2 + sig[:, None].double() ** 2), noise, None)
    t = edm_sigma_steps().double().tolist()
    a = [ti / (s2 + ti * ti) for ti in t]
    gain = t[0]
    for i in range(18):
        h = t[i + 1] - t[i]
        gain *= 1 + h * a[i] if i == 17 else 1 + h * (a[i] + a[i + 1] * (1 + h * a[i])) / 2
    # the sampler forms the step widths t' - t of float32 noise levels in float32 (2^-24 relative
    # each), and the gain is a product of 18 factors of order 1 in them
    torch.testing.assert_close(x, noise * gain, rtol=18 * 2 ** -24, atol=0)
    ode = 80 * math.sqrt(s2) / math.sqrt(s2 + 80 ** 2)
    assert abs(gain / ode - 1) < 0.06


def test_seeded_noise_depends_on_the_sample_seed_only():
    a = SeededNoise([5, 9]).randn((2, 3, 4))
    b = SeededNoise([9]).randn((1, 3, 4))
    assert torch.equal(a[1], b[0])
    assert not torch.equal(a[0], a[1])
    with pytest.raises(ValueError, match="3 for 2 seeds"):
        SeededNoise([1, 2]).randn((3, 4))


def test_churn_is_seeded_through_randn_like():
    def run():
        rnd = SeededNoise([1, 2])
        return edm_sampler(lambda x, s, c: 0.5 * x, rnd.randn((2, 4)), None, S_churn=40, S_min=0.05, S_max=50,
                           S_noise=1.003, randn_like=rnd.randn_like)

    assert torch.equal(run(), run())
    with pytest.raises(ValueError, match="randn_like"):
        edm_sampler(lambda x, s, c: x, torch.randn(2, 4), None, S_churn=40)
