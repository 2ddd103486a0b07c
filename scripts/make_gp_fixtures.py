#!/usr/bin/env python3
"""Generate scikit-learn reference fixtures for the GP tests (tests/gp_reference.rs).

Not run by CI; rerun by hand after changing the datasets:

    pip install scikit-learn
    python3 scripts/make_gp_fixtures.py            # writes tests/fixtures/gp/*.json

Each fixture holds a small seeded dataset (inputs in the unit box), and scikit-learn's
GaussianProcessRegressor results for the kernel

    ConstantKernel(s2) * Matern(length_scale=[...], nu=ν) + WhiteKernel(noise)

with ν = 2.5 (the paper's kernel) unless a fixture's "nu" says 0.5 or 1.5,

with normalize_y=False and alpha=0 (our constant prior mean m is handled by fitting y - m):

* "fixed": at given hyperparameters (optimizer=None): predictive mean, std (latent + noise)
  at test points, and the log marginal likelihood;
* "fitted": after sklearn's own optimisation (L-BFGS-B, n_restarts_optimizer stated, same
  box bounds as precond's defaults): its log marginal likelihood and hyperparameters.
"""
import json
import os
import sys

import numpy as np
import sklearn
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

# precond's default bounds (GpParams::default().bounds).
LS_BOUNDS = (1e-2, 1e2)
SIGNAL_BOUNDS = (1e-6, 1e4)
NOISE_BOUNDS = (1e-6, 1e2)
RESTARTS = 2

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "fixtures", "gp")


def kernel(ls, s2, noise, fixed, nu):
    b = "fixed" if fixed else None
    return ConstantKernel(s2, constant_value_bounds=b or SIGNAL_BOUNDS) * Matern(
        length_scale=ls, length_scale_bounds=b or LS_BOUNDS, nu=nu
    ) + WhiteKernel(noise, noise_level_bounds=b or NOISE_BOUNDS)


def target(x, rng, noise_std):
    f = np.sin(3.0 * x[:, 0]) + 0.5 * x[:, 1] ** 2
    if x.shape[1] > 2:
        f += 0.3 * np.cos(5.0 * x[:, 2])
    if x.shape[1] > 3:
        f += 0.05 * x[:, 3]  # nearly irrelevant dimension
    return f + noise_std * rng.standard_normal(len(x))


def make(name, seed, n, d, noise_std, prior_mean, ls, s2, noise, n_test=25, nu=2.5):
    rng = np.random.default_rng(seed)
    x = rng.uniform(size=(n, d))
    y = target(x, rng, noise_std) + prior_mean
    xt = rng.uniform(size=(n_test, d))
    r = y - prior_mean

    gp = GaussianProcessRegressor(kernel(ls, s2, noise, True, nu), alpha=0.0, optimizer=None, normalize_y=False)
    gp.fit(x, r)
    mu, std = gp.predict(xt, return_std=True)
    lml = gp.log_marginal_likelihood_value_

    start = kernel([0.5] * d, float(np.mean(r**2)), 0.1 * float(np.mean(r**2)), False, nu)
    gpf = GaussianProcessRegressor(start, alpha=0.0, normalize_y=False, n_restarts_optimizer=RESTARTS, random_state=seed)
    gpf.fit(x, r)
    kf = gpf.kernel_
    fitted = {
        "restarts": RESTARTS,
        "lml": float(gpf.log_marginal_likelihood_value_),
        "length_scales": np.atleast_1d(kf.k1.k2.length_scale).tolist(),
        "signal_variance": float(kf.k1.k1.constant_value),
        "noise_variance": float(kf.k2.noise_level),
        "bounds": {"length_scale": LS_BOUNDS, "signal_variance": SIGNAL_BOUNDS, "noise_variance": NOISE_BOUNDS},
    }
    fx = {
        "name": name,
        "generator": "scripts/make_gp_fixtures.py",
        "sklearn_version": sklearn.__version__,
        "seed": seed,
        "nu": nu,
        "prior_mean": prior_mean,
        "x": x.tolist(),
        "y": y.tolist(),
        "x_test": xt.tolist(),
        "fixed": {
            "length_scales": list(ls),
            "signal_variance": s2,
            "noise_variance": noise,
            "lml": float(lml),
            "mean": (mu + prior_mean).tolist(),
            "std": std.tolist(),
        },
        "fitted": fitted,
    }
    os.makedirs(OUT, exist_ok=True)
    with open(os.path.join(OUT, name + ".json"), "w") as fh:
        json.dump(fx, fh, indent=1)
    print(f"{name}: fixed LML {lml:.6f}, fitted LML {fitted['lml']:.6f}", file=sys.stderr)


if __name__ == "__main__":
    make("d2_n40", seed=1, n=40, d=2, noise_std=0.1, prior_mean=0.0, ls=[0.3, 0.6], s2=0.8, noise=0.01)
    make("d3_n60_mean", seed=2, n=60, d=3, noise_std=0.2, prior_mean=0.3, ls=[0.2, 0.5, 1.5], s2=1.3, noise=0.05)
    make("d4_n80_small_noise", seed=3, n=80, d=4, noise_std=0.01, prior_mean=0.0, ls=[0.4, 0.25, 0.9, 2.0], s2=0.5, noise=1e-4)
    make("d2_n40_nu05", seed=4, n=40, d=2, noise_std=0.1, prior_mean=0.0, ls=[0.5, 1.2], s2=0.8, noise=0.01, nu=0.5)
    make("d3_n60_nu15", seed=5, n=60, d=3, noise_std=0.05, prior_mean=0.2, ls=[0.3, 0.7, 1.5], s2=1.1, noise=0.005, nu=1.5)
