"""Saving a model file whose normalization arrays are read-only (a robot spec's home position, as
bench/bench_fuzz.py and the tests pass it): no warning, and the values read back unchanged.

torch warns once per process ("The given NumPy array is not writable") when a tensor is made from a
read-only array, so the save runs in a fresh child process, where an earlier test cannot have used
up that one warning."""
import json
import subprocess
import sys

CHILD = r"""
import json, sys, warnings
import numpy as np, torch
from deepprompt_ros.model.checkpoint import Normalization, load_checkpoint, save_checkpoint
from deepprompt_ros.model.network import DeepProMPNet, ModelConfig

def frozen(values):
    a = np.asarray(values, dtype=np.float64)
    a.setflags(write=False)
    return a

norm = Normalization(frozen([0.1, -0.2]), frozen([0.5, 0.25]), {"object": frozen([1.0, 2.0, 3.0])},
                     {"object": frozen([0.1, 0.2, 0.3])})
torch.manual_seed(0)
net = DeepProMPNet(ModelConfig(n_joints=2, latent_dim=2, hidden=4, context_dims=(("object", 3),)))
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    path = save_checkpoint(sys.argv[1] + "/m.safetensors", net, norm, ["a", "b"])
back = load_checkpoint(path).normalization
print(json.dumps({"warnings": [str(w.message) for w in caught],
                  "y_mean": back.y_mean.tolist(), "y_std": back.y_std.tolist(),
                  "ctx_mean": back.ctx_mean["object"].tolist(), "ctx_std": back.ctx_std["object"].tolist()}))
"""


def test_read_only_normalization_is_saved_without_a_warning_and_read_back(tmp_path):
    run = subprocess.run([sys.executable, "-c", CHILD, str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["warnings"] == [], out["warnings"]
    assert out["y_mean"] == [0.1, -0.2] and out["y_std"] == [0.5, 0.25]
    assert out["ctx_mean"] == [1.0, 2.0, 3.0] and out["ctx_std"] == [0.1, 0.2, 0.3]
