"""Training from a sharded dataset (deepprompt_ros.training.streaming) gives the model the same demos give
in memory (data_workers 0), the same model for any count of worker processes, and bounds what
auto_select and the validation read (recorded in the selection's metadata). The peak memory's
independence of the dataset's size is measured by test/test_bench_data.py (bench/bench_data.py --quick)."""
import dataclasses

import numpy as np
import pytest

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.sharded import write_shards
from deepprompt_ros.data.synthetic import bimodal_sine, iter_image_reach
from deepprompt_ros.model.checkpoint import load_checkpoint
from deepprompt_ros.training.cli import main as train_main
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.basis import init_basis_pca
from deepprompt_ros.training.loop import new_network, train
from deepprompt_ros.training.streaming import bounded_subset, train_sharded
from deepprompt_ros.training.tensors import fit_normalization, to_tensors

QUIET = dict(log=lambda s: None)
#: a fixed linear part (PCA-initialized) and a small network: a few updates of every loss term
CFG = TrainConfig(steps=40, val_every=20, threads=1, batch_size=8, n_points=40, auto_select=False, decoder_basis=10,
                  basis_init="pca", basis_lr_scale=0.0, latent_linear=8, latent_dim=12, hidden=32, n_val=6)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    demos = tuple(iter_image_reach(40, seed=3, n_joints=4, n_points=40, n_images=3, image_size=16))
    shards = write_shards(demos, tmp_path_factory.mktemp("shards") / "s", shard_size=7)
    return DemoDataset(demos), shards


def max_weight_difference(a, b) -> float:
    sa, sb = a.state_dict(), b.state_dict()
    return max(float((sa[k] - sb[k]).abs().max()) for k in sa)


def test_sharded_training_without_workers_equals_training_in_memory(data):
    mem, shards = data
    net_m, norm_m, hist_m = train(mem, CFG, **QUIET)
    net_s, norm_s, hist_s = train_sharded(shards, CFG, **QUIET)
    # the same draws on the same tensors: bitwise equal weights on this machine (0.0 measured)
    assert max_weight_difference(net_m, net_s) <= 1e-6
    np.testing.assert_allclose(norm_s.y_mean, norm_m.y_mean, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(norm_s.y_std, norm_m.y_std, rtol=1e-12)
    # the validation summed in float64 over chunks: 3e-8 relative measured
    for a, b in zip(hist_m, hist_s):
        for k in a["val"]:
            assert b["val"][k] == pytest.approx(a["val"][k], rel=1e-6), (a["step"], k)
        assert b["loss"] == pytest.approx(a["loss"], rel=1e-6)


def test_worker_processes_give_the_same_model_for_any_count(data):
    mem, shards = data
    one = train_sharded(shards, dataclasses.replace(CFG, data_workers=1), **QUIET)
    two = train_sharded(shards, dataclasses.replace(CFG, data_workers=2), **QUIET)
    assert max_weight_difference(one[0], two[0]) == 0.0
    assert [h["val"] for h in one[2]] == [h["val"] for h in two[2]]
    # other batches than without workers (their own generator), a model as good: 11 % apart measured
    ref_net, _, ref_hist = train_sharded(shards, CFG, **QUIET)
    assert two[2][-1]["val"]["mean"] == pytest.approx(ref_hist[-1]["val"]["mean"], rel=0.3)
    assert max_weight_difference(ref_net, two[0]) > 1e-4


def test_auto_select_and_validation_read_bounded_subsets(data, tmp_path):
    _, shards = data
    cfg = dataclasses.replace(CFG, auto_select=True, steps=20, select_max_demos=20, val_max_demos=4)
    info = {}
    train_sharded(shards, cfg, info=info, **QUIET)
    bounded = info["selection"]["bounded"]
    assert bounded == {"train_demos": 34, "held_out_demos": 6, "select_demos": 20, "val_demos": 4, "seed": 0,
                       "select_max_demos": 20, "val_max_demos": 4}
    assert info["selection"]["linear_part"]["cross_validation"]["n_demos"] == 20
    assert info["selection"]["linear_part"]["method"] == "5-fold cross-validation on the 20 training demonstrations"
    assert info["selection"]["residual"]["n_val"] == 4 and info["selection"]["residual"]["judged_on"] == "validation demos"


def test_train_command_on_shards_writes_a_model_that_loads(data, tmp_path):
    _, shards = data
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("auto_select: false\ndecoder_basis: 10\nbasis_init: pca\nbasis_lr_scale: 0.0\nlatent_linear: 8\n"
                   "latent_dim: 12\nhidden: 32\nn_points: 40\nsteps: 10\nval_every: 10\nthreads: 1\n"
                   "data_workers: 2\nbatch_size: 8\n")
    out = tmp_path / "m.safetensors"
    assert train_main(["--data", shards.source, "--config", str(cfg), "--out", str(out)]) == 0
    ckpt = load_checkpoint(out)
    assert ckpt.joint_names == shards.joint_names
    assert ckpt.metadata["provenance"]["n_train"] == 36 and ckpt.metadata["provenance"]["dataset"] == shards.source
    assert ckpt.metadata["train_config"]["data_workers"] == 2
    # the file holds the model the same configuration trains in this process
    same = train_sharded(shards, TrainConfig.from_yaml(cfg), **QUIET)[0]
    assert max_weight_difference(ckpt.build(), same) == 0.0


#: the bimodal sines with the linear part taken within their two modes (the decoder holds the offsets)
MODES_CFG = dataclasses.replace(CFG, decoder_basis=10, latent_linear=4, latent_dim=5, linear_modes=2, n_val=10,
                                steps=30, val_every=30)


@pytest.fixture(scope="module")
def sines(tmp_path_factory):
    mem = bimodal_sine(70, n_points=40, seed=2)
    return mem, write_shards(mem.demos, tmp_path_factory.mktemp("sines") / "s", shard_size=16)


def test_training_within_modes_equals_memory_and_the_modes_of_a_bounded_subset_are_the_decoders(sines):
    mem, shards = sines
    net_m, _, hist_m = train(mem, MODES_CFG, **QUIET)
    net_s, _, hist_s = train_sharded(shards, MODES_CFG, **QUIET)
    assert max_weight_difference(net_m, net_s) <= 1e-6
    assert net_s.cfg.decoder_modes == 2
    np.testing.assert_allclose(net_s.mode_offsets.numpy(), net_m.mode_offsets.numpy(), atol=1e-6)
    assert hist_s[-1]["val"]["mean"] == pytest.approx(hist_m[-1]["val"]["mean"], rel=1e-6)
    # the modes found on 20 of the 60 training demos: the decoder holds that subset's offsets and shares
    train_ids = np.sort(np.random.default_rng(0).permutation(70)[10:])
    select_ids = bounded_subset(train_ids, 20, 0)
    sub = DemoDataset(tuple(mem.demos[i] for i in select_ids))
    norm = fit_normalization(DemoDataset(tuple(mem.demos[i] for i in train_ids)), 40)
    net = new_network(mem, MODES_CFG)
    init_basis_pca(net, to_tensors(sub, norm, 40), n_modes=2)
    bounded = dataclasses.replace(MODES_CFG, select_max_demos=20)
    net_b, _, hist_b = train_sharded(shards, bounded, **QUIET)
    np.testing.assert_allclose(net_b.mode_offsets.numpy(), net.mode_offsets.numpy(), atol=1e-6)
    np.testing.assert_allclose(net_b.mode_cumulative_shares.numpy(), net.mode_cumulative_shares.numpy(), atol=1e-7)
    # the modes of 20 demos serve the validation demos about as well as those of all 60
    assert hist_b[-1]["val"]["mean"] == pytest.approx(hist_s[-1]["val"]["mean"], rel=0.5)
