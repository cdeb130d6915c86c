# Run for docs/results/eegnet_recheck/first_commit_runs.json (see README.md there), e.g.
# (from this repository's root, after `git archive da66553 | tar -x -C /tmp/eeg_old`) PYTHONPATH=/tmp/eeg_old python docs/results/eegnet_recheck/first_commit_train.py 0 1.0 /tmp/old0.npz /tmp/old_s0_q1.json
"""Train EEGNet on dumped epochs at quality q with the code on PYTHONPATH; print metrics."""
import json, sys, time
import numpy as np, torch
seed = int(sys.argv[1]); q = float(sys.argv[2]); npz = sys.argv[3]; out = sys.argv[4]
from services.eeg.calibration import TrainingConfig, train_classifier
from services.eeg.preprocessing import EpochSet, epochs_from_raw
torch.set_num_threads(1)
d = np.load(npz)
X = (d["X0"] + np.float32(q) * (d["X1"] - d["X0"])).astype(np.float32)
import inspect
params = inspect.signature(EpochSet).parameters
import mne; ch = mne.channels.make_standard_montage("biosemi64").ch_names
from services.eeg.preprocessing import PreprocessingParams
epochs = EpochSet(X, d["y"], ch, PreprocessingParams(), 2048.0, synthetic=True)
fields = TrainingConfig.__dataclass_fields__
kw = {"max_epochs": 150} if "max_epochs" in fields else {"max_passes": 150, "decoders": ("eegnet",)}
t = time.process_time(); w = time.perf_counter()
r = train_classifier(epochs, seed=seed, config=TrainingConfig(**kw))
m = r.metrics
res = {k: m.get(k) for k in ("test_accuracy", "balanced_accuracy", "roc_auc", "best_training_epoch", "best_pass", "training_epochs_run", "passes_run")}
res.update(cpu_s=time.process_time() - t, wall_s=time.perf_counter() - w, history=r.history)
json.dump(res, open(out, "w"))
print(out, {k: v for k, v in res.items() if k != "history"}, "val_loss[:3]", r.history["val_loss"][:3])
