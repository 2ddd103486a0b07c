-- Fitted model deviation estimators, one row per version. The training set of version v is the
-- experiment's first `n_train` transitions in id order (transitions are append-only), so
-- `state` (the fitted hyperparameters and, for the heteroscedastic mode, the noise model) plus
-- those transitions rebuild the exact model without re-optimising.
CREATE TABLE models (
    experiment_id            INTEGER NOT NULL REFERENCES experiments (id),
    version                  INTEGER NOT NULL CHECK (version > 0),
    n_train                  INTEGER NOT NULL,
    n_trajectories           INTEGER NOT NULL,
    noise                    TEXT    NOT NULL,
    state                    TEXT    NOT NULL,
    hyperparameters          TEXT    NOT NULL,
    log_marginal_likelihood  REAL    NOT NULL,
    fit_seconds              REAL    NOT NULL,
    fitted_at                TEXT    NOT NULL,
    PRIMARY KEY (experiment_id, version)
);
