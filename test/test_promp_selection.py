"""ProMP's regularizer and via-point noise chosen by cross-validation on its training demonstrations
(deepprompt_ros.baselines.promp_selection) and the ProMP baseline that uses them by default."""
import inspect

import numpy as np
import pytest

from deepprompt_ros.baselines.promp import ProMP
from deepprompt_ros.baselines.promp_model import ProMPModel
from deepprompt_ros.baselines.promp_selection import COV_REG_SCALES, VIA_NOISES, ProMPSelection, select_promp
from deepprompt_ros.baselines.registry import MODEL_CLASSES
from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import Demonstration
from deepprompt_ros.training.basis import PROMP_FORM, cv_score, cv_via_sets, fold_assignment
from deepprompt_ros.training.config import TrainConfig

T = 50
X = np.linspace(0.0, 1.0, T)
D_JOINTS, N_BASIS = 2, 8


def weight_demos(n: int, seed: int) -> np.ndarray:
    """n demos (n, T, 2) exactly in the span of the ProMP basis (8 RBFs per joint), their 16 weights drawn
    from a full-rank Gaussian whose variances fall from 1 to 1e-3: the answer is known — the sample
    covariance of many demos is the truth (no regularizer needed), that of a few spans a few of the
    16 directions (a held-out demo lies mostly outside it: a large regularizer is needed)."""
    d = D_JOINTS * N_BASIS
    q, _ = np.linalg.qr(np.random.default_rng(0).standard_normal((d, d)))
    root = q * np.sqrt(np.geomspace(1.0, 1e-3, d))
    w = (np.random.default_rng(seed).standard_normal((n, d)) @ root.T).reshape(n, D_JOINTS, N_BASIS)
    return np.einsum("tb,njb->ntj", ProMP(D_JOINTS, N_BASIS).basis(X), w)


def test_a_smaller_regularizer_when_the_demos_span_the_weight_space_a_larger_one_for_few_demos():
    many = select_promp(weight_demos(80, 1), X, n_basis=N_BASIS)
    few = select_promp(weight_demos(4, 2), X, n_basis=N_BASIS)
    assert many.cov_reg_scale <= 0.01 and few.cov_reg_scale >= 0.3, (many.cov_reg_scale, few.cov_reg_scale)
    # the choice is the grid's minimum of the score, and every grid point was scored
    for sel in (many, few):
        assert len(sel.table) == len(COV_REG_SCALES) * len(VIA_NOISES)
        best = min(sel.table, key=lambda r: r[2])
        assert (sel.cov_reg_scale, sel.via_noise, sel.cv_mse) == best[:3]
    assert many.folds == 5 and few.folds == 4 and many.n_demos == 80


def test_a_grid_point_scores_the_held_out_reconstructions_of_its_folds():
    Y = weight_demos(9, 3)
    sel = select_promp(Y, X, n_basis=N_BASIS, cov_reg_scales=(0.1,), via_noises=(1e-3, 0.3), folds=3, seed=7)
    fold_of = fold_assignment(9, 3, 7)
    sets = cv_via_sets(T, 9, 5, 2, 7)
    errs = np.zeros((9, 4))
    for f in range(3):
        tr = fold_of != f
        p = ProMP(D_JOINTS, N_BASIS, cov_reg_scale=0.1).fit(Y[tr], X)
        std = np.maximum(Y[tr].reshape(-1, D_JOINTS).std(0), 1e-3)
        for i in np.flatnonzero(~tr):
            for j, s in enumerate(sets[i]):
                m = p.condition(X[s], Y[i, s], noise_var=(1e-3 * std) ** 2).mean_trajectory(X)
                errs[i, j] = ((m - Y[i]) ** 2).mean()
    row = [r for r in sel.table if r[1] == 1e-3][0]
    score, parts = cv_score(errs)
    assert row[2] == pytest.approx(score, rel=1e-9) and row[3:] == pytest.approx(parts, rel=1e-9)
    assert parts[0] > parts[1] > parts[2]  # more points, less error: start, start + end, 5 points
    assert score == pytest.approx(np.prod(parts) ** (1 / 3))
    assert [len(s) for s in sets[0]] == [1, 2, 5, 5] and list(sets[0][1]) == [0, T - 1]
    # a noise of 0.3 of the joints' spread lets the conditioned mean miss the points: worse
    assert [r for r in sel.table if r[1] == 0.3][0][2] > row[2] and sel.via_noise == 1e-3


def test_the_selection_is_given_the_training_demos_alone_and_refuses_too_few():
    params = list(inspect.signature(select_promp).parameters)
    assert params[:2] == ["Y", "x"] and all(p not in params for p in ("val", "test", "held_out"))
    with pytest.raises(ValueError, match=">= 3 demonstrations, got 2"):
        select_promp(weight_demos(2, 0), X, n_basis=N_BASIS)
    with pytest.raises(ValueError, match="grids must be non-empty"):
        select_promp(weight_demos(5, 0), X, n_basis=N_BASIS, via_noises=())


def _dataset(Y: np.ndarray, name: str, scale: float = 1.0) -> DemoDataset:
    return DemoDataset(tuple(Demonstration(f"{name}_{i}", X, scale * y, ("a", "b")) for i, y in enumerate(Y)), name)


def test_the_promp_baseline_selects_on_its_training_split_only_and_keeps_the_choice_in_its_file(tmp_path):
    assert ProMPModel in MODEL_CLASSES and ProMPModel().options.cov_reg_scale == "auto"  # the experiments' default
    # DeepProMP's linear part departs from this baseline's form only on evidence (training.basis.PROMP_FORM)
    assert (ProMPModel().options.n_basis, "raw") == PROMP_FORM
    train = _dataset(weight_demos(12, 4), "train")
    cfg = TrainConfig(n_points=T, seed=3)
    logged = []
    a = ProMPModel(log=logged.append).fit(train, cfg, val_ds=_dataset(weight_demos(3, 5), "val"))
    b = ProMPModel(log=lambda s: None).fit(train, cfg, val_ds=_dataset(weight_demos(3, 6), "val2", scale=10.0))
    assert a.selection == b.selection  # the validation demos play no part in the choice
    direct = select_promp(np.stack([d.resampled(T) for d in train.demos]), X, n_basis=20, seed=3)
    assert a.selection == direct and a.cov_reg_scale == direct.cov_reg_scale and a.via_noise == direct.via_noise
    assert len(logged) == 1 and f"cov_reg_scale {direct.cov_reg_scale:g}" in logged[0] \
        and f"via_noise {direct.via_noise:g}" in logged[0] and "cross-validation on the 12 training demos" in logged[0]
    # conditioning uses the chosen noise, per joint in the normalization's units
    np.testing.assert_allclose(a.via_noise_var, (a.via_noise * np.asarray(a.norm.y_std)) ** 2)
    y = train.demos[0].resampled(T)
    cond = a.condition(X[[0, 20]], y[[0, 20]])
    want = a.promp.condition(X[[0, 20]], y[[0, 20]], noise_var=a.via_noise_var).mean_trajectory(X)
    np.testing.assert_allclose(a.mean_trajectory(cond, X), want)
    a.save(tmp_path / "p.safetensors")
    back = ProMPModel.load(tmp_path / "p.safetensors")
    assert back.selection == a.selection and (back.cov_reg_scale, back.via_noise) == (a.cov_reg_scale, a.via_noise)
    np.testing.assert_allclose(back.mean_trajectory(back.condition(X[[0, 20]], y[[0, 20]]), X), want, atol=1e-12)


def test_given_values_are_used_as_given_and_few_demos_fall_back():
    train = _dataset(weight_demos(6, 4), "train")
    cfg = TrainConfig(n_points=T, n_val=1)
    fixed = ProMPModel(cov_reg_scale=0.2, via_noise=0.01, log=lambda s: None).fit(train, cfg)
    assert fixed.selection is None and (fixed.cov_reg_scale, fixed.via_noise) == (0.2, 0.01)
    half = ProMPModel(cov_reg_scale=0.2, log=lambda s: None).fit(train, cfg)
    assert half.cov_reg_scale == 0.2 and {r[0] for r in half.selection.table} == {0.2}
    logged = []
    tiny = ProMPModel(log=logged.append).fit(_dataset(weight_demos(3, 4), "tiny"), cfg)  # 2 left after validation
    assert tiny.selection is None and "too few to cross-validate" in logged[0]
    with pytest.raises(ValueError, match="via_noise must be 'auto' or a finite number > 0; got 0"):
        ProMPModel(via_noise=0)
    assert isinstance(half.selection, ProMPSelection)
