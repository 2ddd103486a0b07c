-- Two estimators behind the MDE: the exact GP and the sparse GP. Every experiment and model
-- version stored before used the exact GP: their settings say so (`mde.estimator` "exact", with
-- the sparse GP's default 256 inducing points), and their stored state is tagged as the exact
-- GP's.
UPDATE experiments SET settings = json_set(settings, '$.mde.estimator', 'exact')
WHERE json_type(settings, '$.mde.estimator') IS NULL;

UPDATE experiments SET settings = json_set(settings, '$.mde.inducing_points', 256)
WHERE json_type(settings, '$.mde.inducing_points') IS NULL;

UPDATE models SET state = json_set(state, '$.estimator', 'exact')
WHERE json_type(state, '$.estimator') IS NULL;

-- A fit that was not attempted because it would not fit the server's memory budget: the
-- previous version kept answering. Shown on the model endpoint, the timeline and /metrics.
CREATE TABLE fit_refusals (
    id             INTEGER PRIMARY KEY,
    experiment_id  INTEGER NOT NULL REFERENCES experiments (id),
    n_train        INTEGER NOT NULL,
    n_trajectories INTEGER NOT NULL,
    estimator      TEXT    NOT NULL,
    needed_bytes   REAL    NOT NULL,
    budget_bytes   REAL    NOT NULL,
    reason         TEXT    NOT NULL,
    refused_at     TEXT    NOT NULL
);
CREATE INDEX fit_refusals_by_experiment ON fit_refusals (experiment_id, id);
