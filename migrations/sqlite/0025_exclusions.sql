-- Data hygiene: an operator leaves a bad run or a bad calibration day out of an experiment's
-- model, and may bring it back. An exclusion names one trajectory or a time range of ingest
-- times, resolved when it is made into the trajectories it covers (`excluded_trajectories`);
-- it is never deleted, only marked restored, so the table is the audit trail. Each model
-- version records the exclusions in effect when it was fitted (`models.exclusions`, ids
-- comma-separated, NULL for none): its training set is the experiment's first `n_train`
-- transitions in id order outside the trajectories those exclusions cover.
CREATE TABLE exclusions (
    id              INTEGER PRIMARY KEY,
    experiment_id   INTEGER NOT NULL REFERENCES experiments (id),
    trajectory_id   INTEGER REFERENCES trajectories (id),
    from_time       TEXT,
    to_time         TEXT,
    reason          TEXT    NOT NULL,
    n_trajectories  INTEGER NOT NULL CHECK (n_trajectories > 0),
    n_transitions   INTEGER NOT NULL CHECK (n_transitions > 0),
    created_at      TEXT    NOT NULL,
    created_by      TEXT,
    restored_at     TEXT,
    restored_by     TEXT,
    CHECK ((trajectory_id IS NULL) = (from_time IS NOT NULL AND to_time IS NOT NULL))
);
CREATE INDEX exclusions_by_experiment ON exclusions (experiment_id, id);

CREATE TABLE excluded_trajectories (
    exclusion_id   INTEGER NOT NULL REFERENCES exclusions (id),
    trajectory_id  INTEGER NOT NULL REFERENCES trajectories (id),
    PRIMARY KEY (exclusion_id, trajectory_id)
);
CREATE INDEX excluded_trajectories_by_trajectory ON excluded_trajectories (trajectory_id);

ALTER TABLE models ADD COLUMN exclusions TEXT;
