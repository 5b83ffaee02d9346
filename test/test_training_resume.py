"""Resuming a training run (OUT.resume.pt): a run continued from its resume file ends with the same
weights and history as a run never interrupted, after a real SIGKILL too; a resume file that does not
match the run is refused."""
import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from deepprompt_ros.data.synthetic import bimodal_sine
from deepprompt_ros.model.checkpoint import load_checkpoint
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.loop import train
from deepprompt_ros.training.resume import resume_path

QUIET = dict(log=lambda s: None)


def _cfg(**kw):
    base = dict(steps=60, val_every=20, hidden=32, latent_dim=4, n_points=30, threads=1, auto_select=False,
                batch_size=8, kl_anneal_steps=50)
    return TrainConfig(**{**base, **kw})


def _same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def _hist(h):  # the history without its timing
    return [{k: v for k, v in r.items() if k != "samples_per_s"} for r in h]


@pytest.mark.parametrize("auto_select", [False, True])
def test_resumed_run_equals_straight_run(tmp_path, auto_select):
    ds = bimodal_sine(30, n_points=30, seed=2)
    half, full = _cfg(steps=40, auto_select=auto_select), _cfg(steps=80, auto_select=auto_select)
    net_s, _, hist_s = train(ds, full, out_path=tmp_path / "straight.safetensors", **QUIET)
    out = tmp_path / "resumed.safetensors"
    train(ds, half, out_path=out, **QUIET)  # 40 updates, a multiple of val_every: validated where the 80-update run is
    saved = torch.load(resume_path(out), weights_only=True)
    assert [f["step"] for f in saved["fits"]][0] == 40
    net_r, _, hist_r = train(ds, full, out_path=out, resume=True, **QUIET)
    _same(net_s.state_dict(), net_r.state_dict())  # bitwise: the same updates from the same states
    assert _hist(hist_s) == _hist(hist_r)
    assert [h["step"] for h in hist_r] == [20, 40, 60, 80]
    assert load_checkpoint(out).metadata["train_config"] == load_checkpoint(
        tmp_path / "straight.safetensors").metadata["train_config"]
    # a run that completed resumes to its own end without training again
    net_again, _, hist_again = train(ds, full, out_path=out, resume=True, **QUIET)
    _same(net_s.state_dict(), net_again.state_dict())


def test_resume_refuses_missing_and_mismatching_files(tmp_path):
    ds = bimodal_sine(30, n_points=30, seed=2)
    out = tmp_path / "m.safetensors"
    with pytest.raises(ValueError, match=r"--resume: no resume file .*m\.resume\.pt"):
        train(ds, _cfg(), out_path=out, resume=True, **QUIET)
    train(ds, _cfg(steps=20), out_path=out, **QUIET)
    with pytest.raises(ValueError, match=r"reached update 20, beyond this run's steps = 10: expected steps >= 20"):
        train(ds, _cfg(steps=10), out_path=out, resume=True, **QUIET)
    with pytest.raises(ValueError, match=r"does not match this run: configuration keys differ: lr 0\.001 -> 0\.002"):
        train(ds, _cfg(lr=2e-3), out_path=out, resume=True, **QUIET)
    with pytest.raises(ValueError, match="its demonstrations .* differ from this run's"):
        train(bimodal_sine(30, n_points=30, seed=3), _cfg(), out_path=out, resume=True, **QUIET)
    resume_path(out).write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="is not a readable resume file"):
        train(ds, _cfg(), out_path=out, resume=True, **QUIET)


def _cli(tmp_path, out, *extra, steps=400):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("val_every: 100\ncheckpoint_every: 20\nhidden: 32\nlatent_dim: 4\nthreads: 1\nn_points: 30\n"
                   "auto_select: false\nbatch_size: 8\n")
    data = tmp_path / "data"
    if not data.is_dir():
        bimodal_sine(30, n_points=30, seed=2).save(data)
    return [sys.executable, "-m", "deepprompt_ros.training.cli", "--data", str(data), "--config", str(cfg),
            "--out", str(out), "--steps", str(steps), *extra]


def test_killed_run_resumes_to_the_uninterrupted_result(tmp_path):
    straight = tmp_path / "straight.safetensors"
    subprocess.run(_cli(tmp_path, straight), check=True, capture_output=True, timeout=120)
    out = tmp_path / "killed.safetensors"
    proc = subprocess.Popen(_cli(tmp_path, out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if resume_path(out).is_file() and torch.load(resume_path(out), weights_only=True)["fits"][0]["step"] >= 100:
                break
            time.sleep(0.05)
    finally:
        os.kill(proc.pid, signal.SIGKILL) if proc.poll() is None else None
        proc.wait()
    step = torch.load(resume_path(out), weights_only=True)["fits"][0]["step"]
    assert proc.returncode == -signal.SIGKILL and 100 <= step < 400, (proc.returncode, step)
    assert not out.exists()  # killed before its end
    done = subprocess.run(_cli(tmp_path, out, "--resume"), capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert f"resumed from {resume_path(out)} at update {step}" in done.stdout
    _same(load_checkpoint(straight).state_dict, load_checkpoint(out).state_dict)
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["best_val_mse_rad2"] == load_checkpoint(straight).metadata["metrics"]["best_val_mse_rad2"]


def test_cli_resume_errors_exit_2(tmp_path):
    out = tmp_path / "m.safetensors"
    proc = subprocess.run(_cli(tmp_path, out, "--resume", steps=20), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "error: --resume: no resume file" in proc.stderr, proc.stderr
    subprocess.run(_cli(tmp_path, out, steps=20), check=True, capture_output=True, timeout=120)
    (tmp_path / "other.yaml").write_text("hidden: 16\nthreads: 1\nn_points: 30\nauto_select: false\nbatch_size: 8\n"
                                         "latent_dim: 4\n")
    cmd = _cli(tmp_path, out, "--resume", steps=20)
    cmd[cmd.index("--config") + 1] = str(tmp_path / "other.yaml")
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "configuration keys differ: hidden 32 -> 16" in proc.stderr, proc.stderr


def test_an_entry_written_keeps_its_states_when_the_training_goes_on(tmp_path):
    """The file's entries are copies: the weights and optimizer states a fit recorded stay as they were when the
    network is changed afterwards (the best weights loaded at the fit's end), when the next fit's save rewrites
    the file."""
    from deepprompt_ros.training.distributed import SINGLE
    from deepprompt_ros.training.resume import ResumeFile
    net = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(net.parameters())
    net(torch.ones(1, 3)).sum().backward()
    opt.step()
    last = {k: t.clone() for k, t in net.state_dict().items()}
    gen = torch.Generator().manual_seed(0)
    ckpt = ResumeFile(tmp_path / "r.resume.pt", SINGLE, load=False)
    ckpt.save(0, {"step": 1, "net": net.state_dict(), "optimizer": opt.state_dict()}, [gen])
    with torch.no_grad():
        net.weight.zero_()
        opt.state[net.weight]["exp_avg"].zero_()
    ckpt.save(1, {"step": 1, "net": net.state_dict(), "optimizer": opt.state_dict()}, [gen])
    fits = torch.load(tmp_path / "r.resume.pt", weights_only=True)["fits"]
    _same(fits[0]["net"], last)
    assert fits[0]["optimizer"]["state"][0]["exp_avg"].abs().min() > 0
    assert torch.equal(fits[1]["net"]["weight"], torch.zeros(2, 3))
