-- An experiment's further models (`settings.models`) each label every posted transition: one
-- row per (transition, model), written in the transaction that stores the transition. A model
-- that could not answer leaves its label missing (`s_pred` and `deviation` NULL) and says why
-- (`missing`) — the transition is stored all the same. The transitions table, and so every
-- single-model experiment's rows, is unchanged.
CREATE TABLE model_labels (
    experiment_id  INTEGER NOT NULL REFERENCES experiments (id),
    transition_id  INTEGER NOT NULL REFERENCES transitions (id),
    model          TEXT    NOT NULL,
    s_pred         TEXT,
    deviation      REAL,
    missing        TEXT,
    PRIMARY KEY (transition_id, model),
    CHECK ((s_pred IS NULL) = (deviation IS NULL)),
    CHECK ((deviation IS NULL) = (missing IS NOT NULL))
);
CREATE INDEX model_labels_by_experiment ON model_labels (experiment_id, transition_id);

-- Each fitted version holds one deviation estimator per further model with labels, fitted in
-- the same fit job on the labelled ones among the version's training transitions; stored in
-- the transaction that stores the version (`models`), rebuilt with it.
CREATE TABLE further_fits (
    experiment_id            INTEGER NOT NULL,
    version                  INTEGER NOT NULL,
    model                    TEXT    NOT NULL,
    n_train                  INTEGER NOT NULL CHECK (n_train > 0),
    label_cap                REAL    NOT NULL,
    log_marginal_likelihood  REAL    NOT NULL,
    state                    TEXT    NOT NULL,
    PRIMARY KEY (experiment_id, version, model),
    FOREIGN KEY (experiment_id, version) REFERENCES models (experiment_id, version)
);
