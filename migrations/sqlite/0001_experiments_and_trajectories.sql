-- Experiments, executed trajectories and their transitions, and idempotency records.
-- Vectors are stored as JSON arrays of numbers (TEXT); times as RFC 3339 UTC strings.

-- One experiment: a domain, its learning settings and a seed. `settings` holds the fully
-- resolved settings JSON exactly as the API shows them, so a restarted server continues exactly.
CREATE TABLE experiments (
    id          INTEGER PRIMARY KEY,
    name        TEXT    NOT NULL,
    settings    TEXT    NOT NULL,
    created_at  TEXT    NOT NULL
);

-- One executed trajectory (possibly partial, possibly unsolicited). Written in one transaction
-- with all its transitions.
CREATE TABLE trajectories (
    id             INTEGER PRIMARY KEY,
    experiment_id  INTEGER NOT NULL REFERENCES experiments (id),
    proposal_id    INTEGER,
    partial        INTEGER NOT NULL DEFAULT 0 CHECK (partial IN (0, 1)),
    n_transitions  INTEGER NOT NULL CHECK (n_transitions > 0),
    created_at     TEXT    NOT NULL
);
CREATE INDEX trajectories_by_experiment ON trajectories (experiment_id, id);

-- One (s, a, s') with the model's prediction and the deviation label d(f̂(s,a), s') that the
-- server computed on ingest. `id` order is ingest order, which is also the MDE's training order.
CREATE TABLE transitions (
    id             INTEGER PRIMARY KEY,
    experiment_id  INTEGER NOT NULL REFERENCES experiments (id),
    trajectory_id  INTEGER NOT NULL REFERENCES trajectories (id),
    step           INTEGER NOT NULL,
    s              TEXT    NOT NULL,
    a              TEXT    NOT NULL,
    s_next         TEXT    NOT NULL,
    s_pred         TEXT    NOT NULL,
    deviation      REAL    NOT NULL,
    UNIQUE (trajectory_id, step)
);
CREATE INDEX transitions_by_experiment ON transitions (experiment_id, id);

-- A retried POST with the same Idempotency-Key returns the stored response and stores nothing.
-- `request` is the canonical JSON of the first request, to refuse a key reused with another body.
CREATE TABLE idempotency_keys (
    experiment_id  INTEGER NOT NULL REFERENCES experiments (id),
    key            TEXT    NOT NULL,
    request        TEXT    NOT NULL,
    status         INTEGER NOT NULL,
    response       TEXT    NOT NULL,
    created_at     TEXT    NOT NULL,
    PRIMARY KEY (experiment_id, key)
);
