"""Why the learned-weights alternation did not stop: per re-registration, how many pairs change
their whole lateral permutation (null slots included), how many change their real-lateral
correspondence, and how far rotations move.

    python benchmarks/learn_convergence.py plate|conditions|species [quick]
"""

import sys
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
import rootshape_jax as rs
import rootshape_jax._learn as L

sys.path.insert(0, str(Path(__file__).parent))
from bench_learn import labelled_sets

tag = sys.argv[1]
quick = len(sys.argv) > 2 and sys.argv[2] == "quick"
roots, labels, _ = labelled_sets([tag], quick)[tag]
trees = rs.batch(roots, n_points=32, normalise_scale=True)
print(tag, len(roots), trees.capacity, flush=True)
saved = []
orig = L._Fitter.register


def reg(self, w, I, J, desc):
    r = orig(self, w, I, J, desc)
    saved.append((w, r))
    return r


L._Fitter.register = reg
t0 = time.perf_counter()
res = rs.learn_weights(trees, labels, max_reregistrations=5, tol=0.0, progress=False)
print("wall", time.perf_counter() - t0, "status", res.status, "nrereg", res.n_reregistrations)
print("loss_trace", res.loss_trace, "inner", res.inner_loss_trace)
print("changed", res.changed_pairs, "gain", res.registration_gain)
mask = np.asarray(trees.mask)
for k in range(1, len(saved)):
    (w0, a), (w1, b) = saved[k - 1], saved[k]
    full = np.any(a.permutation != b.permutation, axis=1)
    real = L.correspondence_changed(a, b, mask)
    dR = np.abs(a.rotation - b.rotation).reshape(len(a.rotation), -1).max(axis=1)
    rel = np.abs(a.energy - b.energy) / np.maximum(b.energy, 1e-300)
    print(
        f"step {k}: λ {dict((n, round(float(v), 4)) for n, v in w1.items())}; full-perm changed {full.sum()}, real-corr changed {real.sum()} of {len(full)}; "
        f"rotation changed >1e-6 in {(dR > 1e-6).sum()} (max {dR.max():.3g}); in re-matched pairs median rel. energy change {np.median(rel[real]) if real.any() else 0:.3g}"
    )
    if real.any():
        idx = np.flatnonzero(real)[:5]
        for i in idx:
            print(
                "   pair",
                a.first[i],
                a.second[i],
                "nreal",
                mask[a.first[i]].sum(),
                mask[a.second[i]].sum(),
                "dR",
                dR[i],
            )
