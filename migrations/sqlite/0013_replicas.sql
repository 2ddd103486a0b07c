-- What several replicas over one database need (PostgreSQL; SQLite gets the same schema so both
-- engines run the same queries):
-- * proposals and refusals keep the figures the dashboard lists as columns, instead of reading
--   them out of the stored JSON with SQLite's JSON functions;
-- * fit_jobs: one row per experiment whose model needs a fit. A replica claims the row to fit
--   (the right to fit: one fitter per experiment), heartbeats while it fits, and deletes the
--   row when done; a claim whose heartbeat stopped (the replica died) is taken over.

ALTER TABLE proposals ADD COLUMN n_actions INTEGER;
ALTER TABLE proposals ADD COLUMN extensions INTEGER;
UPDATE proposals SET n_actions = json_array_length(body, '$.trajectory.actions'),
                     extensions = json_extract(body, '$.extensions');

ALTER TABLE refusals ADD COLUMN first_beta REAL;
UPDATE refusals SET first_beta = json_extract(betas, '$[0]');

CREATE TABLE fit_jobs (
    experiment_id       INTEGER PRIMARY KEY REFERENCES experiments (id),
    -- Raised by every request: a claim that started at an older generation fits again.
    generation          INTEGER NOT NULL,
    -- Fit even when a model already covers the latest complete batch (a client asked).
    forced              INTEGER NOT NULL CHECK (forced IN (0, 1)),
    requested_at        TEXT    NOT NULL,
    -- The replica fitting, the generation it claimed, and its last sign of life (Unix s).
    claimed_by          TEXT,
    claimed_generation  INTEGER,
    heartbeat_unix      REAL
);
