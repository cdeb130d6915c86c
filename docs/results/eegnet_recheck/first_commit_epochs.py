# Run for docs/results/eegnet_recheck/first_commit_runs.json (see README.md there), e.g.
# (from this repository's root, after `git archive da66553 | tar -x -C /tmp/eeg_old`) PYTHONPATH=/tmp/eeg_old python docs/results/eegnet_recheck/first_commit_epochs.py 0 /tmp/old0.npz
"""Dump seed-s epochs at quality 0 and 1 from the code on sys.path[0] (PYTHONPATH)."""
import hashlib, sys, time
import numpy as np
seed = int(sys.argv[1]); out = sys.argv[2]
from benchmarks.bench_eeg import random_labels
from services.eeg.preprocessing import epochs_from_raw
from services.eeg.virtual_subject import simulate_recording
t=time.process_time()
labels = random_labels(600, 0.3, seed)
e0 = epochs_from_raw(simulate_recording(labels, quality=0.0, seed=seed))
e1 = epochs_from_raw(simulate_recording(labels, quality=1.0, seed=seed))
np.savez(out, X0=e0.X, X1=e1.X, y=e0.y)
print(out, e0.X.shape, hashlib.sha256(e0.X.tobytes()).hexdigest()[:16], hashlib.sha256(e1.X.tobytes()).hexdigest()[:16], e0.y.sum(), "cpu", time.process_time()-t)
