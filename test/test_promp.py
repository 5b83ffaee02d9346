"""Tests of deepprompt_ros.baselines.promp (seeded, numbers and properties)."""
import numpy as np
import pytest

from deepprompt_ros.baselines.promp import ProMP, TrajectoryDistribution

T = 100
X = np.linspace(0.0, 1.0, T)


def demos(n, d=7, seed=0, rhythmic=False):
    """Sine-shaped 7-joint demonstrations varying by offset, amplitude and a slow drift."""
    rng = np.random.default_rng(seed)
    scale = np.linspace(0.5, 1.5, d)
    out = []
    for _ in range(n):
        amp = 1.0 + rng.normal(0, 0.1)
        off = rng.normal(0, 0.1, d)
        drift = 0.0 if rhythmic else rng.normal(0, 0.2) * X[:, None] ** 2
        out.append(off + amp * scale * np.sin(2 * np.pi * X)[:, None] + drift)
    return np.stack(out)


@pytest.fixture(scope="module")
def promp():
    return ProMP(7, 20).fit(demos(20), X)


def test_via_point_conditioning_passes_through_and_shrinks_the_std(promp):
    xv = np.array([0.1, 0.3, 0.5, 0.7, 0.9])
    yv = promp.mean_trajectory(xv) + np.array([0.2, -0.1, 0.15, 0.05, -0.2])[:, None]
    before = promp.mean_trajectory(X).copy()
    tight = promp.condition(xv, yv, noise_var=1e-8)
    assert np.abs(tight.mean_trajectory(xv) - yv).max() <= 1e-4
    assert np.array_equal(promp.mean_trajectory(X), before)          # a new object was returned
    cond = promp.condition(xv, yv, noise_var=1e-6)
    std_via = cond.std_trajectory(xv)
    assert np.all(std_via <= 1e-3) and np.all(std_via >= 0.5e-3)     # ~ sqrt(noise_var)
    assert np.all(promp.std_trajectory(xv) > 20 * std_via)            # it was wide before
    # between via-points the uncertainty stays larger than at them
    assert np.all(cond.std_trajectory([0.2]) > 2 * std_via.max())


def test_sequential_conditioning_equals_joint_conditioning(promp):
    xa, xb = np.array([0.2, 0.6]), np.array([0.4, 0.9, 1.0])
    ya = promp.mean_trajectory(xa) + 0.1
    yb = promp.mean_trajectory(xb) - 0.05
    seq = promp.condition(xa, ya, 1e-4).condition(xb, yb, 1e-4)
    both = promp.condition(np.r_[xa, xb], np.vstack([ya, yb]), 1e-4)
    assert np.allclose(seq.mean_trajectory(X), both.mean_trajectory(X), atol=1e-9)
    assert np.allclose(seq.std_trajectory(X), both.std_trajectory(X), atol=1e-9)
    assert np.allclose(seq.cov_w, both.cov_w, atol=1e-10)


def test_joint_mask_conditions_only_the_selected_joints(promp):
    yv = np.full((1, 7), np.nan)
    yv[0, 2] = 1.5                                                   # only joint_3 given
    mask = np.zeros(7, dtype=bool)
    mask[2] = True
    cond = promp.condition([0.25], yv, 1e-8, joint_mask=mask)
    assert cond.mean_trajectory([0.25])[0, 2] == pytest.approx(1.5, abs=1e-4)
    assert np.all(np.isfinite(cond.mean_trajectory(X)))
    with pytest.raises(ValueError, match="via-point 0 has value nan for joint_1"):
        promp.condition([0.25], yv, 1e-8)                             # NaN of an observed joint


def test_rank_deficient_fit_conditions_without_oscillation():
    Y = demos(3, seed=1)                       # 3 demos, 7·20 = 140 weights: covariance rank 2
    p = ProMP(7, 20).fit(Y, X)
    assert p.cov_reg_used > 0
    np.linalg.cholesky(p.cov_w)                # the regularized covariance is positive definite
    xv = np.array([0.05, 0.3, 0.5, 0.7, 0.95])
    # via-points off the span of the three demos: a different offset per joint and point
    offsets = np.random.default_rng(2).uniform(-0.3, 0.3, (5, 7))
    yv = Y[0][np.searchsorted(X, xv)] + offsets
    c = p.condition(xv, yv, noise_var=1e-8)
    m, s = c.mean_trajectory(X), c.std_trajectory(X)
    assert np.all(np.isfinite(m)) and np.all(np.isfinite(s))
    assert np.abs(c.mean_trajectory(xv) - yv).max() <= 1e-4
    data_range = np.abs(Y).max() + 0.3
    assert np.abs(m).max() <= 1.5 * data_range
    # no oscillation: the conditioned mean does not move faster than the demos by much
    speed = np.abs(np.diff(m, axis=0)).max()
    assert speed <= 3 * np.abs(np.diff(Y, axis=1)).max()
    # without the regularizer the same via-points cannot be reached
    p0 = ProMP(7, 20, cov_reg=0.0).fit(Y, X)
    assert np.abs(p0.condition(xv, yv, noise_var=1e-8).mean_trajectory(xv) - yv).max() > 1e-2


def test_context_conditioning_recovers_the_demo_of_that_context():
    rng = np.random.default_rng(3)
    C = rng.uniform(-1, 1, (12, 2))

    def demo(c):  # a family linear in the context
        return (np.outer(np.sin(2 * np.pi * X), [1.0 + 0.5 * c[0], -0.3 * c[1], 0.2])
                + np.outer(X, [c[1], c[0], c[0] - c[1]]))

    Y = np.stack([demo(c) for c in C])
    p = ProMP(3, 15).fit(Y, X, contexts=C)
    assert p.context_dim == 2
    fit_rms = np.sqrt(p.obs_var.max())                                # basis approximation error
    for k in (0, 5, 11):
        got = p.condition_context(C[k]).mean_trajectory(X)
        assert np.sqrt(np.mean((got - Y[k]) ** 2)) < 2 * fit_rms < 4e-3
    new_c = np.array([0.3, -0.4])                                     # not a training context
    got = p.condition_context(new_c)
    assert np.sqrt(np.mean((got.mean_trajectory(X) - demo(new_c)) ** 2)) < 2 * fit_rms
    # exactly (up to 1e-5) the basis fit of the true demonstration of that context
    projection = ProMP(3, 15).fit(demo(new_c)[None], X).mean_trajectory(X)
    assert np.abs(got.mean_trajectory(X) - projection).max() < 1e-5
    assert got.context_dim == 0
    assert got.std_trajectory(X).max() < 0.5 * p.std_trajectory(X).max()
    with pytest.raises(ValueError, match="context has 3 values; .* has 2"):
        p.condition_context([0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="without contexts"):
        ProMP(3, 15).fit(Y, X).condition_context(new_c)


def test_periodic_basis_has_no_seam():
    p = ProMP(7, 15, rhythmic=True).fit(demos(10, rhythmic=True), X)
    for deriv in (0, 1, 2):
        assert np.allclose(p.mean_trajectory([0.0], deriv), p.mean_trajectory([1.0], deriv),
                           rtol=0, atol=1e-9)
    assert np.allclose(p.std_trajectory([0.0]), p.std_trajectory([1.0]), atol=1e-12)
    # a discrete RBF basis on the same data is not periodic in its derivative
    r = ProMP(7, 15).fit(demos(10, rhythmic=True) + X[None, :, None], X)
    assert np.abs(r.mean_trajectory([0.0]) - r.mean_trajectory([1.0])).max() > 0.5


@pytest.mark.parametrize("rhythmic", [False, True])
def test_basis_derivatives_match_finite_differences(rhythmic):
    p = ProMP(2, 12, rhythmic=rhythmic)
    x = np.linspace(0.02, 0.98, 40)
    h = 1e-5
    f0, fp, fm = p.basis(x), p.basis(x + h), p.basis(x - h)
    assert np.allclose(f0.sum(axis=1), 1.0)                           # normalized
    assert np.allclose(p.basis(x, 1), (fp - fm) / (2 * h), atol=1e-5)
    assert np.allclose(p.basis(x, 2), (fp - 2 * f0 + fm) / h ** 2, atol=2e-3 * np.abs(p.basis(x, 2)).max())


def test_blend_weights_select_each_primitive(promp):
    other = ProMP(7, 20).fit(demos(15, seed=5) + 0.5, X)
    first = promp.distribution(X)
    second = other.distribution(X)
    b1 = promp.blend(other, lambda x: np.ones_like(x), X)
    b0 = promp.blend(other, lambda x: np.zeros_like(x), X)
    assert isinstance(b1, TrajectoryDistribution)
    assert np.allclose(b1.mean, first.mean, atol=1e-9) and np.allclose(b1.cov, first.cov, atol=1e-12)
    assert np.allclose(b0.mean, second.mean, atol=1e-9) and np.allclose(b0.cov, second.cov, atol=1e-12)
    ramp = promp.blend(other, lambda x: 1.0 - x, X)                   # first -> second over time
    assert np.allclose(ramp.mean[0], first.mean[0], atol=1e-9)
    assert np.allclose(ramp.mean[-1], second.mean[-1], atol=1e-9)
    mid = promp.blend(other, 0.5 * np.ones(T), X)
    # the product of Gaussians is narrower than either factor
    assert np.all(mid.std <= np.maximum(first.std, second.std) + 1e-12)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        promp.blend(other, 1.5 * np.ones(T), X)


def test_samples_follow_the_distribution_and_are_reproducible(promp):
    s1 = promp.sample(X, 4000, np.random.default_rng(7))
    s2 = promp.sample(X, 4000, np.random.default_rng(7))
    assert s1.shape == (4000, T, 7) and np.array_equal(s1, s2)
    std = promp.std_trajectory(X)
    assert np.all(np.abs(s1.mean(axis=0) - promp.mean_trajectory(X)) <= 5 * std / np.sqrt(4000) + 1e-12)
    assert np.allclose(s1.std(axis=0), std, rtol=0.1)


def test_save_load_round_trip(tmp_path, promp):
    cond = promp.condition([0.3, 0.8], promp.mean_trajectory([0.3, 0.8]) + 0.1, 1e-6)
    for p in (promp, cond):
        path = tmp_path / "p.npz"
        p.save(path)
        q = ProMP.load(path)
        assert np.array_equal(q.mean_trajectory(X), p.mean_trajectory(X))
        assert np.allclose(q.std_trajectory(X), p.std_trajectory(X), rtol=0, atol=1e-15)
        assert np.array_equal(q.cov_w, p.cov_w) and np.array_equal(q.obs_var, p.obs_var)
        assert (q.n_basis, q.rhythmic, q.joint_names, q.n_demos) == (p.n_basis, p.rhythmic,
                                                                     p.joint_names, p.n_demos)
        xv, yv = [0.5], promp.mean_trajectory([0.5]) - 0.2
        assert np.array_equal(q.condition(xv, yv).mean_trajectory(X),
                              p.condition(xv, yv).mean_trajectory(X))
    with np.load(tmp_path / "p.npz", allow_pickle=False) as z:          # plain arrays, no pickle
        assert z["meta"].dtype.kind == "U"


def test_variable_length_demos_fit_like_resampled_ones():
    Y = demos(6, d=2)
    lists_Y = [Y[i, :: (i % 3) + 1] for i in range(6)]
    lists_x = [X[:: (i % 3) + 1] for i in range(6)]
    a = ProMP(2, 10).fit(lists_Y, lists_x)
    b = ProMP(2, 10).fit(Y, X)
    assert np.abs(a.mean_trajectory(X) - b.mean_trajectory(X)).max() < 0.01


def test_errors_say_what_is_wrong_and_what_is_expected(promp):
    with pytest.raises(ValueError, match="5 joint values; this ProMP has 7 joints"):
        promp.condition([0.5], np.zeros((1, 5)))
    with pytest.raises(ValueError, match=r"x_via\[1\] = 1.2 is outside \[0, 1\]"):
        promp.condition([0.5, 1.2], np.zeros((2, 7)))
    with pytest.raises(ValueError, match="empty"):
        promp.condition([], np.zeros((0, 7)))
    with pytest.raises(ValueError, match=r"outside \[0, 1\]"):
        promp.mean_trajectory([-0.1, 0.5])
    Y = demos(3)
    with pytest.raises(ValueError, match="has 7 joints; this ProMP has 6"):
        ProMP(6, 10).fit(Y, X)
    Y_nan = Y.copy()
    Y_nan[1, 4, 2] = np.nan
    with pytest.raises(ValueError, match="demonstration 1 has value nan at sample 4 for joint_3"):
        ProMP(7, 10).fit(Y_nan, X)
    with pytest.raises(ValueError, match="no demonstrations"):
        ProMP(7, 10).fit(np.zeros((0, T, 7)), X)
    with pytest.raises(ValueError, match="not fitted"):
        ProMP(7, 10).mean_trajectory(X)
    with pytest.raises(ValueError, match="n_basis"):
        ProMP(7, 1)
